"""``graphcal track DATASET --out DIR``: run the legged EKF over a dataset's timeseries and write

* ``trajectory.tum``  -- the estimate, TUM format ``t x y z qx qy qz qw`` (T_world_body), at
  ``tum_rate_hz`` (default 100 Hz; every sample with 0);
* ``metrics.json``    -- ``ape_rmse_m``, ``rpe_rmse_m``, ``drift_percent``, ``distance_m``,
  ``nees_mean`` (null when the dataset has no truth), NIS, whiteness, real-time factor, ...;
* ``trajectory.png``, ``errors.png``, ``nis.png`` -- plots;
* ``report.md``       -- a short report;
* ``stairs.json``     -- on a stairs dataset, the stairs model of :mod:`graphcal.locomotion.stairs` from the
  keyframe clouds (:func:`stairs_keyframes`) placed with the estimated poses, with per-tread errors
  against the truth's ascending flight (:func:`ascending_flight`) when there is a truth.

The outputs are written as one atomic set (:func:`graphcal.io.atomic.atomic_directory`); an
existing ``DIR`` is replaced only if it is empty or holds a previous ``graphcal track`` output
(``metrics.json`` with ``format: graphcal-track/1`` and nothing else graphcal did not write).
Truth is read from ``truth.yaml`` beside the dataset (simulated data) by the evaluation only.
"""


from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.io.atomic import atomic_directory, atomic_write_bytes, check_output_folder, previous_output_files
from graphcal.locomotion.track import ascending_flight, stairs_keyframes, track, tum_text

__all__ = ["TRACK_FORMAT", "OUTPUT_FILES", "run"]

log = logging.getLogger(__name__)

TRACK_FORMAT = "graphcal-track/1"
OUTPUT_FILES = ("trajectory.tum", "metrics.json", "trajectory.png", "errors.png", "nis.png", "report.md",
                "stairs.json")


def _check_out(out: Path, overwrite: bool) -> None:
    """The output-folder policy of graphcal.io.atomic.check_output_folder, for a track output."""
    check_output_folder(out, lambda f: previous_output_files(f, "metrics.json", OUTPUT_FILES, TRACK_FORMAT),
                        what="graphcal track output", overwrite=overwrite)


# ----------------------------------------------------------------------------- plots
def _figures(result, truth, series, nees_t, nees, nees_dof):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from graphcal.locomotion.metrics import chi2_band, pose_errors

    def png(fig) -> bytes:
        import io

        FigureCanvasAgg(fig)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110)
        return buf.getvalue()

    est = result.T_world_body[:, :3, 3]
    t = result.times
    out = {}
    # trajectory: top view and height
    fig = Figure(figsize=(10, 4.2))
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    if truth is not None:
        ax1.plot(truth.T_world_body[:, 0, 3], truth.T_world_body[:, 1, 3], "k-", lw=2.5, alpha=0.35, label="truth")
        ax2.plot(truth.times, truth.T_world_body[:, 2, 3], "k-", lw=2.5, alpha=0.35, label="truth")
    ax1.plot(est[:, 0], est[:, 1], "C0-", lw=1, label="estimate")
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("y (m)")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.set_title("body trajectory, top view (world)")
    ax1.legend(loc="best")
    ax2.plot(t, est[:, 2], "C0-", lw=1, label="estimate")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("z (m)")
    ax2.set_title("body height")
    fig.tight_layout()
    out["trajectory.png"] = png(fig)

    # errors with the filter's 3-sigma
    fig = Figure(figsize=(10, 6))
    ci = result.cov_index
    sig = np.sqrt(np.maximum(np.diagonal(result.cov_pose, axis1=1, axis2=2), 0.0))
    axp, axr = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    labels = ("x", "y", "z")
    if truth is not None:
        from graphcal.locomotion.metrics import interp_truth

        e = pose_errors(result.T_world_body[ci], interp_truth(truth, t[ci]))
        for k in range(3):
            axp.plot(t[ci], 1e3 * e[:, k], f"C{k}-", lw=0.8, label=f"{labels[k]} error")
            axr.plot(t[ci], np.degrees(e[:, 3 + k]), f"C{k}-", lw=0.8, label=f"rot {labels[k]} error")
    for k in range(3):
        axp.plot(t[ci], 3e3 * sig[:, k], f"C{k}:", lw=0.8)
        axp.plot(t[ci], -3e3 * sig[:, k], f"C{k}:", lw=0.8)
        axr.plot(t[ci], 3 * np.degrees(sig[:, 3 + k]), f"C{k}:", lw=0.8)
        axr.plot(t[ci], -3 * np.degrees(sig[:, 3 + k]), f"C{k}:", lw=0.8)
    axp.set_ylabel("position (mm)")
    axr.set_ylabel("orientation (deg)")
    axr.set_xlabel("time (s)")
    axp.set_title("estimate - truth (solid) and the filter's 3 sigma (dotted)" if truth is not None
                  else "the filter's 3 sigma (no truth)")
    if truth is not None:
        axp.legend(loc="upper left", fontsize=8)
        axr.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out["errors.png"] = png(fig)

    # NIS
    fig = Figure(figsize=(10, 5))
    ax = fig.add_subplot(2, 1, 1)
    if len(result.stance_nis):
        lo, hi = chi2_band(result.stance_dof)
        ax.plot(result.stance_times, result.stance_nis, ".", ms=1.5, alpha=0.4, color="C0", label="stance NIS")
        w = max(1, len(result.stance_nis) // 200)
        if w > 1:
            m = np.convolve(result.stance_nis, np.ones(w * 5) / (w * 5), mode="same")
            ax.plot(result.stance_times, m, "C1-", lw=1, label="running mean")
        ax.axhline(result.stance_dof, color="k", lw=0.8, label=f"dof {result.stance_dof}")
        ax.axhspan(lo, hi, color="g", alpha=0.1, label="95 % band")
        ax.set_ylim(0, max(3 * hi, 1))
    ax.set_ylabel("NIS")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("normalised innovation squared (stance kinematics; ICP below)")
    ax = fig.add_subplot(2, 1, 2)
    if len(result.icp_nis):
        ax.plot(result.icp_times, result.icp_nis, "o", ms=3, label="ICP NIS")
        ax.plot(result.icp_times, result.icp_dof, "k_", ms=8, label="dof (directions fused)")
    if nees is not None and len(nees):
        ax.plot(nees_t, nees, "-", color="C3", lw=0.8, label=f"pose NEES (dof {nees_dof})")
    ax.set_xlabel("time (s)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no ICP updates, no truth", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    out["nis.png"] = png(fig)
    return out


def _stairs_model(ds, inp, result, truth, *, max_clouds: int = 20):
    """The stairs model (graphcal.locomotion.stairs) from the keyframe clouds (:func:`stairs_keyframes`)
    placed with the estimate, compared with the truth's ascending flight when there is a truth.
    Errors of the model become {"error": ...}."""
    from graphcal.locomotion import stairs as stairs_mod

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
        doc = dict(stairs_mod.stairs_to_json(model, errors))
        if compared is not None:
            found = {e.true_index for e in errors if e.true_index >= 0}
            compared["all_true_treads_found"] = found == set(range(len(compared["true_treads"])))
            doc["truth_compared"] = compared
    except GraphcalError as exc:
        doc = {"error": str(exc)}
    doc.update(meta)
    return doc


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


def run(dataset: str | Path, out: str | Path, *, progress: bool = True, config=None,
        tum_rate_hz: float = 100.0, overwrite: bool = True, stairs: bool = True) -> str:
    """The ``graphcal track`` command (see the module docstring). Returns a short summary.

    Raises:
        DatasetError: the dataset is malformed or lacks what the filter needs (file and field named).
        OutputExistsError: ``out`` is not empty and not a previous track output.
    """
    from graphcal.locomotion.metrics import chi2_band, load_truth, nees_against_truth, trajectory_metrics, whiteness

    out = Path(out)
    if not (np.isfinite(tum_rate_hz) and tum_rate_hz >= 0):
        raise GraphcalError(f"--tum-rate must be a finite number >= 0 (Hz; 0 = every sample), got {tum_rate_hz}")
    _check_out(out, overwrite)
    ds, inp, res = track(dataset, config=config, progress=progress)
    truth = load_truth(ds.root) if ds.root is not None else None

    m: dict = {"format": TRACK_FORMAT, "dataset": str(dataset), "truth": truth is not None}
    series = None
    nees_t = nees = None
    nees_dof = 6
    est_len = float(np.linalg.norm(np.diff(res.T_world_body[:, :3, 3], axis=0), axis=1).sum())
    if truth is not None:
        tm = trajectory_metrics(res.times, res.T_world_body, truth)
        series = tm.pop("_series")
        m.update(tm)
        m["distance_source"] = "truth"
        nees_t, nees = nees_against_truth(res, truth)
        lo, hi = chi2_band(nees_dof)
        m.update({
            "nees_mean": float(nees.mean()) if len(nees) else None,
            "nees_dof": nees_dof,
            "nees_band_95_single": [lo, hi],
            "nees_fraction_in_band": float(np.mean((nees >= lo) & (nees <= hi))) if len(nees) else None,
        })
    else:
        m.update({"ape_rmse_m": None, "ape_max_m": None, "rpe_rmse_m": None, "drift_percent": None,
                  "final_error_m": None, "distance_m": est_len, "distance_source": "estimate",
                  "nees_mean": None, "nees_dof": nees_dof, "nees_band_95_single": None,
                  "nees_fraction_in_band": None})
    m["distance_estimated_m"] = est_len
    white = whiteness(res.stance_innovations)
    white.pop("autocorr", None)
    lo_s, hi_s = chi2_band(res.stance_dof)
    m.update({
        "stance_nis_mean": float(res.stance_nis.mean()) if len(res.stance_nis) else None,
        "stance_nis_dof": res.stance_dof,
        "stance_nis_fraction_in_band": float(np.mean((res.stance_nis >= lo_s) & (res.stance_nis <= hi_s)))
        if len(res.stance_nis) else None,
        "stance_updates": int(len(res.stance_nis)),
        "innovation_whiteness": white,
        "icp_updates": int(len(res.icp_nis)),
        "icp_rejected": int(res.n_icp_rejected),
        "icp_nis_mean": float(res.icp_nis.mean()) if len(res.icp_nis) else None,
        "icp_dof_mean": float(res.icp_dof.mean()) if len(res.icp_dof) else None,
        "support_switches": int(np.count_nonzero(np.diff(res.support_group))),
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
    files: dict[str, bytes] = {"trajectory.tum": tum_text(res.times[keep], res.T_world_body[keep]).encode()}
    # the metrics are of the filter (every sample), not of the thinned file: evo on trajectory.tum
    # at --tum-rate 10 matches a tenth of the poses and reads a slightly different RMS
    m["metrics_samples"] = "every filter sample (n_samples), whatever --tum-rate"
    m["tum_samples"] = int(len(keep))
    for name, data in _figures(res, truth, series, nees_t, nees, nees_dof).items():
        files[name] = data
    if stairs_doc is not None:
        files["stairs.json"] = json.dumps(_clean(stairs_doc), indent=2).encode()
    names = sorted(list(files) + ["metrics.json", "report.md"])
    m["output_files"] = names
    m = _clean(m)
    files["metrics.json"] = (json.dumps(m, indent=2) + "\n").encode()
    files["report.md"] = _report(m, stairs_doc).encode()

    with atomic_directory(out, overwrite=True) as tmp:
        for name, data in files.items():
            atomic_write_bytes(tmp / name, data)
        _check_out(out, overwrite)
    lines = [f"tracked {dataset}: {m['n_samples']} samples, {m['duration_s']:.1f} s in {m['processing_s']:.1f} s "
             f"({m['real_time_factor']:.1f}x real time); wrote {out}"]
    if m["truth"]:
        lines.append(f"  against the truth: APE {1e3 * m['ape_rmse_m']:.1f} mm RMS, drift {m['drift_percent']:.3f} % "
                     f"of {m['distance_m']:.2f} m, NEES mean {m['nees_mean']:.2f} (dof {nees_dof})")
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
    return "\n".join(lines)


def _report(m: dict, stairs_doc) -> str:
    def f(v, fmt, scale=1.0, unit=""):
        return "n/a (no truth)" if v is None else f"{format(v * scale, fmt)}{unit}"

    w = m.get("innovation_whiteness") or {}
    lines = [
        "# graphcal track",
        "",
        f"Dataset: `{m['dataset']}`; {m['n_samples']} samples over {m['duration_s']:.2f} s, processed in "
        f"{m['processing_s']:.2f} s ({m['real_time_factor']:.1f}x real time).",
        "",
        "Filter: error-state EKF (filterpy), IMU propagation, stance-tripod kinematics (support from joint "
        "torques), ICP between keyframe clouds as relative-pose measurements (docs/state_estimation.md).",
        "",
        "## Accuracy" + ("" if m["truth"] else " (no truth.yaml beside the dataset: the keys that need it are null)"),
        "",
        f"- distance: {m['distance_m']:.2f} m ({m['distance_source']})",
        f"- APE (RMS, no alignment): {f(m.get('ape_rmse_m'), '.2f', 1e3, ' mm')}",
        f"- RPE over {m.get('rpe_delta_m', 1.0)} m (RMS): {f(m.get('rpe_rmse_m'), '.2f', 1e3, ' mm')}",
        f"- drift (final error / distance): {f(m.get('drift_percent'), '.3f', 1.0, ' %')}",
        f"- pose NEES mean: {f(m.get('nees_mean'), '.2f')} (dof 6; fraction of samples inside the single-sample "
        f"95 % band: {f(m.get('nees_fraction_in_band'), '.3f')})",
        "",
        "## Consistency",
        "",
        f"- stance NIS mean {f(m.get('stance_nis_mean'), '.2f')} (dof {m['stance_nis_dof']}), "
        f"{m['stance_updates']} updates, {m['support_switches']} support switches",
        f"- innovation whiteness: {f(w.get('fraction_inside'), '.3f')} of the autocorrelations at lags "
        f"1..{w.get('lags')} inside +-1.96/sqrt(n) (white: 0.95); max |rho| {f(w.get('max_abs_autocorr'), '.3f')}",
        f"- ICP: {m['icp_updates']} fused (mean NIS {f(m.get('icp_nis_mean'), '.2f')}, "
        f"{f(m.get('icp_dof_mean'), '.1f')} directions on average), {m['icp_rejected']} rejected",
        "",
        "Plots: trajectory.png, errors.png, nis.png. Trajectory: trajectory.tum (TUM: t x y z qx qy qz qw).",
    ]
    if stairs_doc is not None:
        lines += ["", "## Stairs", ""]
        if "error" in stairs_doc:
            lines.append(f"stairs model failed: {stairs_doc['error']}")
        else:
            kf = stairs_doc.get("keyframes", {})
            lines.append(f"{stairs_doc.get('n_clouds_used')} of {stairs_doc.get('n_clouds_available')} clouds "
                         f"({kf.get('method', '')}), placed with the estimate, stitched by ICP (graphcal.locomotion.stairs).")
            lines.append("")
            for t in stairs_doc.get("treads", []):
                line = (f"- tread {t.get('index')}: height {1e3 * t['height_m']:.1f} mm, depth "
                        f"{1e3 * t['depth_m']:.1f} mm{'' if t.get('depth_complete') else ' (visible extent)'}, "
                        f"width {1e3 * t['width_m']:.1f} mm (visible)")
                e = t.get("errors")
                if e and e.get("true_index", -1) >= 0:
                    dep = e.get("depth_error_m")
                    line += (f"; against true tread {e['true_index']}: height {1e3 * e['height_error_m']:+.1f} mm, "
                             f"depth {'n/a' if dep is None else format(1e3 * dep, '+.1f') + ' mm'}")
                elif e:
                    line += "; no true tread within 5 cm of its height"
                lines.append(line)
            tc = stairs_doc.get("truth_compared")
            if tc:
                lines.append("")
                lines.append(f"Compared with the truth's {tc['flight']} flight ({tc['selection']}); all its treads found: "
                             f"{'yes' if tc.get('all_true_treads_found') else 'NO'}. {tc['note']}.")
    return "\n".join(lines) + "\n"
