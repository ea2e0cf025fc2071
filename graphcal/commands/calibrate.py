"""``graphcal calibrate DATASET --out DIR``: calibrate the sensors (and with ``legs`` the legs) of a
dataset, batch or incremental (:func:`graphcal.calibration.session.calibrate_session`), and write
calibration.yaml, the calibrated URDF, the ROS 2 static transforms and report.html
(:func:`graphcal.report.write.write_calibration_outputs`). :func:`run` returns a
:class:`CalibrateResult`; its ``summary_text()`` is what the command line prints."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.calibration.result import CalibrationResult
from graphcal.calibration.session import calibrate_session
from graphcal.errors import GraphcalError
from graphcal.report.scene_mcap import DEFAULT_MAX_POINTS as SCENE_MAX_POINTS
from graphcal.report.write import check_output_folder, write_calibration_outputs

__all__ = ["run", "CalibrateResult", "GROUP_WORDS", "covariance_scale_text", "noise_lines", "verdict_lines",
           "verdict_warning", "range_scale_warnings"]

#: noise groups (noise_estimation.py) in the words of calibrate's summary line
GROUP_WORDS = {"stance_foot/joint": "joints", "stance_foot/contact": "contact", "imu": "IMU",
               "commanded": "commanded pose"}


def covariance_scale_text(scale: float) -> str:
    """The summary's words for a sensor covariance multiplied by ``scale`` (a variance factor > 1,
    :func:`graphcal.calibration.noise_check.given_noise_check`): the factor, the sigma factor, and
    what they mean (it said "covariance x1 (its plane residuals outgrew ...)" for x1.004)."""
    digits = ".3g" if scale >= 1.01 else ".4f"
    return (f"covariance x{scale:{digits}} (sigma x{np.sqrt(scale):{digits}}): at their fixed point the plane "
            f"residuals are {np.sqrt(scale):{digits}} times the given noise, so every sigma was scaled up"
            + ("; negligible" if scale < 1.01 else ""))


def verdict_warning(result) -> str:
    """The adequacy warning of ``result`` (the first of its warnings), or ""."""
    from graphcal.calibration.adequacy import misfit_warning

    a = getattr(result, "adequacy", None)
    return misfit_warning(a) if a is not None else ""


def verdict_lines(result) -> list[str]:
    """The first lines of calibrate's summary: the adequacy verdict (calibration.yaml ``adequacy:``)
    and, when the model does not fit or gross stations were left out, the warning naming the group
    and the next step."""
    a = getattr(result, "adequacy", None)
    if a is None:
        return []
    head = (f"model {a.verdict.upper() if not a.fits else a.verdict}: worst group {a.worst_group or 'none'}, "
            f"{a.reference} statistic {a.statistic:.4g}, p = {a.p_value:.2g} (noise judged against the "
            "physical noise, not the learned one)")
    lines = [head]
    w = verdict_warning(result)
    if w:
        lines.append(f"warning: {w}")
    lines += [f"warning: {x}" for x in range_scale_warnings(result)]
    return lines


def range_scale_warnings(result) -> list[str]:
    """The warnings of the sensors whose range scale these data do not determine
    (calibration/range_observability.py), printed with the verdict."""
    from graphcal.calibration.range_observability import range_scale_warning

    checks = [getattr(s, "range_scale_check", None) for s in result.sensors.values()]
    return [w for w in (range_scale_warning(c) for c in checks if c is not None) if w]



@dataclass(frozen=True)
class CalibrateResult:
    """What ``graphcal calibrate`` did.

    Attributes:
        calibration: the library's result (warnings, ``noise_source`` and all), as written.
        dataset: the dataset folder, as given.
        out: the output folder.
        files: the files written (calibration.yaml, robot_calibrated.urdf, static_transforms.sh, report.html).
        warnings: every warning of the summary: the misfit warning, the range-scale warnings, then
            the rest of ``calibration.warnings``.
        verdict: the model's adequacy (``fits`` / ``does not fit``), or None when not judged.
        incremental: the incremental mode (iSAM2) was used.
        noise_from: the ``calibration.yaml`` whose noise model was given (``--noise-from``), or None.
        truth: on simulated data (a ``truth.yaml`` beside the dataset), per sensor the error against
            the hidden truth (:func:`truth_comparison`); None otherwise.
    """

    calibration: CalibrationResult
    dataset: str
    out: Path
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None
    incremental: bool = False
    noise_from: str | None = None
    truth: dict | None = None

    def summary_text(self) -> str:
        """The console summary: the verdict, the sensors' poses and sigma, the residuals, the noise
        model, the warnings not said with the verdict, the files."""
        result = self.calibration
        lines = verdict_lines(result)
        lines.append(f"calibrated {len(result.sensors)} sensor(s) from {self.dataset} ({result.solver}); "
                     f"wrote {self.out}:")
        lines += walk_lines(result)
        for name, s in result.sensors.items():
            lines.append(
                f"  {name}: xyz {np.round(s.T_body_sensor[:3, 3], 4).tolist()} m, "
                f"sigma rot {np.round(s.sigma_rot_deg, 3).tolist()} deg, xyz {np.round(s.sigma_xyz_mm, 2).tolist()} mm"
                + time_offset_text(s))
        if np.isfinite(result.normal_rms_deg):
            lines.append(f"  residuals after: normal {result.normal_rms_deg:.3g} deg RMS, distance "
                         f"{result.distance_rms_mm:.3g} mm RMS")
        else:  # laser scanners only: their residuals are point distances, not planes
            lines.append("  residuals after: no plane residuals (laser scan points only)")
        lines += noise_lines(result, self.noise_from, self.incremental)
        if result.outliers:
            lines.append(f"  outlier stations: {', '.join(map(str, result.outliers))}")
        # the misfit warning is printed first (verdict_lines), not again here
        said = {verdict_warning(result), *range_scale_warnings(result)}
        lines += [f"  warning: {w}" for w in result.warnings if w not in said]
        lines += truth_lines(self.truth)
        lines.append("  files: " + ", ".join(sorted(p.name for p in self.files)))
        return "\n".join(lines)


def _walking_dataset(dataset):
    """The dataset read, when it is a walk (clouds in timeseries.csv, no stations.csv); else None."""
    from graphcal.calibration.walking import is_walking_dataset
    from graphcal.io.dataset import Dataset, read_dataset

    ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
    return ds if is_walking_dataset(ds) else None


def walk_contacts(ds, robot) -> np.ndarray:
    """(N, n_feet) bool stance of every timeseries row: the ``force_<foot>`` columns through each
    foot's learned thresholds when there, else ``contact_<foot>`` > 0.5, else the feet's loads from
    the joint torques (locomotion/support.py) through learned thresholds; one line naming the file
    when none is there for every foot."""
    from graphcal.errors import DatasetError

    t = ds.timeseries
    where = (ds.root / "timeseries.csv") if ds.root is not None else "timeseries.csv"
    if all(t.has(f"force_{f}") for f in robot.feet):
        from graphcal.locomotion.contact_detection import detect_contacts

        signals = np.column_stack([t[f"force_{f}"] for f in robot.feet])
        return np.asarray(detect_contacts(signals, np.asarray(t["time"]), robot.feet).mask, dtype=bool)
    if all(t.has(f"contact_{f}") for f in robot.feet):
        return np.column_stack([np.asarray(t[f"contact_{f}"]) > 0.5 for f in robot.feet])
    joints = [j for f in robot.feet for j in robot.leg(f).joint_names]
    if all(t.has(f"tau_{j}") for j in joints):
        from graphcal.locomotion.contact_detection import detect_contacts
        from graphcal.locomotion.support import foot_loads

        loads = foot_loads(robot, {j: np.asarray(t[f"q_{j}"]) for j in joints},
                           {j: np.asarray(t[f"tau_{j}"]) for j in joints}, robot.feet)
        return np.asarray(detect_contacts(loads, np.asarray(t["time"]), robot.feet).mask, dtype=bool)
    missing = [f for f in robot.feet if not t.has(f"contact_{f}") and not t.has(f"force_{f}")]
    raise DatasetError(where, f"header, column force_{(missing or robot.feet)[0]}",
                       "the stance of every foot for a walk's calibration: force_<foot> (N or raw counts), "
                       "contact_<foot> (0/1) or the joint torques tau_<joint> of every foot", "missing")


def _calibrate_walk(ds, *, legs, incremental, ground_roughness_m, plane_max_points, noise_from, progress,
                    time_offsets_s):
    """The walking dataset ``ds`` calibrated (:func:`graphcal.calibration.walk_calibration.calibrate_walk`)."""
    from graphcal.calibration.graph import CalibrationOptions, options_for_ground_roughness
    from graphcal.calibration.walk_calibration import calibrate_walk
    from graphcal.io.dataset import load_dataset_robot

    for flag, given in (("--incremental", incremental), ("--legs", legs), ("--noise-from", noise_from is not None)):
        if given:
            raise GraphcalError(f"{flag} is not supported on a walking dataset yet ({ds.root}: clouds along a walk); "
                                "calibrate it without, or from still stations")
    ground = str((ds.ground or {}).get("type", "level"))
    if ground != "level":  # every stance foot is held on the plane z = 0: stairs would fit as a wrong pose
        raise GraphcalError(f"{ds.root}/dataset.yaml ground.type {ground!r}: calibrating from a walk models a level "
                            "floor under every stance foot; walk on a level floor, or calibrate from still stations")
    unknown = sorted(set(time_offsets_s or {}) - set(ds.sensors))
    if unknown:
        raise GraphcalError(f"--time-offset-ms {unknown[0]}=...: no such sensor in {ds.root}/dataset.yaml "
                            f"(sensors: {', '.join(ds.sensors)})")
    robot = load_dataset_robot(ds)
    options = options_for_ground_roughness(CalibrationOptions(), ground_roughness_m)
    return calibrate_walk(ds, robot, walk_contacts(ds, robot), options=options, time_offsets_s=time_offsets_s,
                          progress=progress, plane_max_points=plane_max_points)


def truth_comparison(dataset: str | Path, result) -> dict | None:
    """Per sensor of ``result`` with a pose in ``truth.yaml`` beside the dataset (simulated data): the
    rotation (deg) and translation (mm) errors of T_body_sensor and the extrinsic NEES (6 dof) of its
    covariance (:func:`graphcal.solvers.covariance.extrinsic_errors`); None without a truth.yaml."""
    import yaml

    from graphcal.io.calibration_yaml import pose_from_dict
    from graphcal.solvers.covariance import extrinsic_errors

    path = Path(dataset) / "truth.yaml"
    if not path.is_file():
        return None
    try:
        sensors = (yaml.safe_load(path.read_text(encoding="utf-8")) or {}).get("sensors") or {}
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    out = {}
    for name, s in result.sensors.items():
        truth = sensors.get(name, {}).get("T_body_sensor") if isinstance(sensors.get(name), dict) else None
        if truth is None:
            continue
        e = extrinsic_errors(s.T_body_sensor, pose_from_dict(truth), s.covariance)
        out[name] = {"rotation_error_deg": e["angle_deg"], "translation_error_mm": e["distance_mm"],
                     "nees": float(e["nees"])}
        true_offset = sensors[name].get("time_offset_s")
        if getattr(s, "time_offset_s", None) is not None and isinstance(true_offset, (int, float)):
            out[name]["time_offset_error_ms"] = 1e3 * (s.time_offset_s - float(true_offset))
    return out or None


def walk_lines(result) -> list[str]:
    """The summary's line on a walking dataset's stations (none for stations)."""
    w = getattr(result, "walk", None)
    if not w:
        return []
    frames = ", ".join(f"{s} {n} of {w['frames_in_log'][s]} frames" for s, n in w["frames"].items())
    return [f"  walk: {w['duration_s']:.1f} s; {frames} taken with >= 3 feet standing; {w['stations']} stations "
            "(the frames and one per change of stance)"]


def time_offset_text(s) -> str:
    """``, time offset ...`` of a walk's camera (empty for stations)."""
    if getattr(s, "time_offset_s", None) is None:
        return ""
    if s.time_offset_source == "estimated":
        return f", time offset {1e3 * s.time_offset_s:+.2f} +- {1e3 * s.time_offset_sigma_s:.2f} ms (stamp minus capture)"
    return f", time offset {1e3 * s.time_offset_s:+.2f} ms ({s.time_offset_source})"


def truth_lines(truth: dict | None) -> list[str]:
    """The summary's comparison with the simulator's truth.yaml (none without one)."""
    if not truth:
        return []
    from graphcal.stats import ppf

    lo, hi = float(ppf(0.025, 6)), float(ppf(0.975, 6))
    return ["  against the truth (truth.yaml beside the dataset): " + "; ".join(
        f"{n} {t['rotation_error_deg']:.4f} deg, {t['translation_error_mm']:.2f} mm, NEES {t['nees']:.2f}"
        + (f", time offset {t['time_offset_error_ms']:+.2f} ms off" if "time_offset_error_ms" in t else "")
        for n, t in truth.items()) + f" (6 dof: one run falls in [{lo:.2f}, {hi:.1f}] 95 % of the time)"]


def noise_lines(result, noise_from, incremental: bool) -> list[str]:
    """The summary's lines on the noise model: learned, given (``noise_from``) or the defaults
    (``incremental``), what the residuals point to, the covariance scales, the groups not learned."""
    lines = []
    if result.noise:
        n = result.noise
        how = (f"noise from {noise_from} (not learned)" if noise_from is not None
               else "noise (defaults; the incremental mode does not learn it: see --noise-from)" if incremental
               else "noise learned from the data")
        learned = [g for g in result.noise_groups if g.status == "learned"]
        if noise_from is None and not incremental and result.noise_groups:
            # only what was learned: a dataset without joint angles or an IMU has no such group
            if learned:
                lines.append(f"  {how}: " + ", ".join(f"{GROUP_WORDS.get(g.group, g.group)} {g.values_text()}"
                                                      for g in learned))
            shared = sorted({" and ".join(GROUP_WORDS.get(k, k) for k in sorted((g.group, *g.shared_with)))
                             for g in result.noise_groups if g.shared_with})
            for words in shared:
                lines.append(f"  {words} noise scaled together: the data do not separate them")
        else:
            lines.append(f"  {how}: joints {np.degrees(n['sigma_joint_rad']):.3f} deg, "
                         f"contact {1e3 * n['sigma_contact_m']:.2f} mm, IMU {np.degrees(n['sigma_imu_rad']):.3f} deg")
    held = [g for g in result.noise_groups if g.status not in ("learned", "given")]
    given = [g for g in result.noise_groups if g.status == "given"]
    if given:
        lines.append("  the residuals point to (given sigma x, one update at the solution): " + ", ".join(
            f"{g.group} {g.data_scale:.3g}" for g in given))
    for name, s in result.sensors.items():
        if s.covariance_scale > 1.0:
            lines.append(f"  {name}: {covariance_scale_text(s.covariance_scale)}")
    if held:
        lines.append("  noise not learned: " + "; ".join(
            f"{g.group} {g.values_text()} ({g.status}, {g.dof:.1f} dof; "
            f"the residuals point to {g.data_scale:.2g}x)" for g in held))
    return lines


def run(dataset: str | Path, out_dir: str | Path, *, legs: bool = False, incremental: bool = False,
        progress: bool = True, ground_roughness_m: float = 0.0,
        plane_max_points: int | None = None, noise_from: str | Path | None = None,
        scene_max_points: int | None = SCENE_MAX_POINTS, time_offsets_s: dict | None = None) -> CalibrateResult:
    """The ``graphcal calibrate`` command: calibrate and write the outputs.

    Args:
        dataset: dataset folder.
        out_dir: output folder (created; a previous graphcal calibration there is replaced only at the end).
        legs: also estimate the leg joint offsets and link lengths.
        incremental: iSAM2, one station at a time, with change detection.
        progress: progress bars (tqdm) and one log line per solve.
        ground_roughness_m: RMS bump height of the ground (m), see
            :func:`graphcal.calibration.graph.options_for_ground_roughness`.
        plane_max_points: see :func:`graphcal.calibration.calibrate.calibrate`.
        noise_from: an earlier ``calibration.yaml`` whose noise model is used as given, not learned
            (:func:`graphcal.calibration.noise_file.options_with_noise_from`).
        scene_max_points: each station's cloud in scene.mcap evenly thinned to at most this many
            points (None: every point; graphcal.report.scene_mcap).
        time_offsets_s: a walking dataset: sensor -> its known time offset (s, stamp minus capture),
            not estimated (the others are).

    Returns:
        a :class:`CalibrateResult` (the calibration, the files written, warnings, verdict).
    """
    check_output_folder(out_dir)  # refuse early, before the work (checked again when writing)
    if noise_from is not None and Path(out_dir).resolve() in Path(noise_from).resolve().parents:
        raise GraphcalError(f"--noise-from {noise_from} is inside --out {out_dir}, whose contents calibrate "
                            "replaces: the file would be lost; copy it elsewhere or choose another --out")
    walk = _walking_dataset(dataset)
    if walk is not None:
        result = _calibrate_walk(walk, legs=legs, incremental=incremental, ground_roughness_m=ground_roughness_m,
                                 plane_max_points=plane_max_points, noise_from=noise_from, progress=progress,
                                 time_offsets_s=time_offsets_s)
    elif time_offsets_s:
        raise GraphcalError("--time-offset-ms belongs to a walking dataset (clouds in timeseries.csv, no "
                            f"stations.csv); {dataset} has stations")
    else:
        result = calibrate_session(dataset, legs=legs, incremental=incremental, ground_roughness_m=ground_roughness_m,
                                   plane_max_points=plane_max_points, noise_from=noise_from, progress=progress)
    written = write_calibration_outputs(result, out_dir, scene_max_points=scene_max_points)
    first = [w for w in (verdict_warning(result), *range_scale_warnings(result)) if w]
    a = getattr(result, "adequacy", None)
    return CalibrateResult(calibration=result, dataset=str(dataset), out=Path(out_dir), files=tuple(written.values()),
                           warnings=tuple(dict.fromkeys([*first, *result.warnings])),
                           verdict=a.verdict if a is not None else None, incremental=incremental,
                           noise_from=None if noise_from is None else str(noise_from),
                           truth=truth_comparison(dataset, result))
