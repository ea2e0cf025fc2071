"""``graphcal calibrate``: from a dataset to the pose of every sensor on the body, with covariance.

Batch mode: build the graph (graph.py), solve it with Levenberg–Marquardt driven from Python
(solvers/batch.py) under a Huber loss, list the measurements that fail a chi-square test as outliers
and solve again without them, then read the marginal covariances (solvers/covariance.py).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from graphcal.geometry import from_gtsam_pose
from graphcal.io.dataset import off_plane_scan_warning
from graphcal.calibration.graph import (CalibrationOptions, CalibrationProblem, build_problem, extrinsic_prior_for_observability,
                    predicted_plane_errors)
from graphcal.calibration.ground_selection import ground_choice_warnings
from graphcal.calibration.measurements import CalibrationData, calibration_data, require_sensors
from graphcal.calibration.result import (
    CalibrationResult,
    ExtrinsicSegment,
    LegEstimate,
    NoiseGroupEstimate,
    SensorEstimate,
    StationResidual,
)

if TYPE_CHECKING:
    import gtsam


def _outlier_measurements(problem: CalibrationProblem, values, options: CalibrationOptions) -> tuple[set, dict]:
    """(measurements failing the chi-square test, chi2 per measurement) at ``values``."""
    from graphcal import stats as chi2_dist
    from graphcal.solvers.batch import whitened_errors

    idx = list(problem.plane_factors)
    errs = whitened_errors(problem.graph, values, idx)
    # one vectorised quantile call (~0.2 ms a call through scipy.stats: 10 ms on Chai's 52 planes)
    limits = chi2_dist.ppf(options.outlier_p, [problem.graph.at(i).dim() for i in idx])
    bad, stats = set(), {}
    for i, e, limit in zip(idx, errs, np.atleast_1d(limits)):
        m = problem.plane_factors[i]
        stats[m] = float(e)
        if e > limit:
            bad.add(m)
    return bad, stats


def _passing_again(ds, robot, data: CalibrationData, options: CalibrationOptions, problem: CalibrationProblem,
                   values, excluded: frozenset) -> set:
    """The left-out measurements that pass the chi-square test at ``values``, the solution of
    ``problem`` (built without them) under ``options``: each measurement's innovation, whitened by its
    own noise plus the uncertainty of the variables it sees (their joint marginal in ``problem``),
    the test of the change detector (:func:`~graphcal.calibration.change_detection.innovation_nis`).
    Tested against its own noise alone, a good plane fails: the body pose it would have moved is
    far less certain than the plane."""
    import gtsam

    from graphcal import stats as chi2_dist
    from graphcal.calibration.change_detection import innovation_nis, joint_covariance

    full = build_problem(ds, robot, data, options, initial=values)
    try:
        marginals = gtsam.Marginals(problem.graph, values)
    except RuntimeError:  # an undetermined direction (gtsam's IndeterminantLinearSystem): keep them out
        return set()

    back = set()
    for i, m in full.plane_factors.items():
        if m in excluded:
            nis, dof = innovation_nis(full.graph.at(i), full.initial, lambda keys: joint_covariance(marginals, keys))
            if nis <= chi2_dist.ppf(options.outlier_p, dof):
                back.add(m)
    return back


log = logging.getLogger(__name__)


def solve_problem(problem: CalibrationProblem, *, progress: bool = False, stage: str = "solve"):
    """Levenberg–Marquardt on a built problem; returns the solver result. With ``progress`` one line
    per solve is logged (INFO)."""
    from graphcal.solvers.batch import solve_lm

    result = solve_lm(problem.graph, problem.initial)
    if progress:
        log.info(f"calibrate: {stage}: {problem.graph.size()} factors, {result.iterations} LM iterations, "
                 f"error {result.error_initial:.4g} -> {result.error_final:.4g}")
    return result


def plane_source_warnings(plane_max_points: int | None, planes_given: bool, ds, fitted=None) -> list[str]:
    """The warnings about where the planes came from: that ``plane_max_points`` did nothing (the
    planes were passed in, ``planes_given``, or the dataset ``ds`` has planes.csv, so no cloud was
    fitted), and which stations with a camera cloud have no plane: planes.csv has none for them (the
    clouds are not read when planes.csv exists: a planes.csv cut short or out of date silently drops
    them), or, when the clouds were fitted, no plane was found in theirs (``fitted``: the
    ``(station, sensor)`` keys of the fitted planes; too few points, collinear points, no plane)."""
    out = []
    if plane_max_points is not None and (planes_given or ds.planes is not None):
        out.append(f"--plane-points {plane_max_points} (plane_max_points) had no effect: the planes were "
                   + ("given" if planes_given else "read from planes.csv, not fitted to the clouds"))
    if planes_given or ds.root is None or (ds.planes is None and fitted is None):
        return out
    from graphcal.clouds.plane_table import camera_clouds_without_planes, no_plane_found_warning, stations_text

    if ds.planes is not None:
        have = zip(ds.planes["sensor"].tolist(), ds.planes["station"].tolist())
    else:
        have = ((sensor, station) for station, sensor in fitted)
    for sensor, (missing, total) in camera_clouds_without_planes(ds, have).items():
        if ds.planes is not None:
            out.append(f"{sensor}: planes.csv has no plane for {len(missing)} of the {total} stations with a "
                       f"cloud ({stations_text(missing)}); they are not used: when planes.csv exists the clouds are not read "
                       "(if it is out of date, delete it or refit it with graphcal extract-planes --out NEW)")
        else:
            out.append(no_plane_found_warning(sensor, missing, total, "those stations are not used"))
    return out


def calibrate(
    dataset,
    *,
    options: CalibrationOptions = CalibrationOptions(),
    progress: bool = False,
    data: CalibrationData | None = None,
    plane_max_points: int | None = None,
) -> CalibrationResult:
    """Calibrate every sensor of a dataset (and the legs with ``options.legs``) in batch.

    Args:
        dataset: a dataset folder, or a :class:`graphcal.io.dataset.Dataset` already read.
        options: noise models and switches.
        progress: print progress to stderr.
        data: the dataset's measurements when already gathered (skips reading clouds again).
        plane_max_points: fit each cloud's planes on at most this many of its points (every k-th;
            None: all). Ignored when the dataset has planes.csv or ``data`` is given. Measured on
            Chai-scale clouds (258k points): 50000 took 0.5-0.6x the time, the translation error grew
            35 % (RMS over 24 datasets, docs/calibration.md).
    """
    from graphcal.io.dataset import Dataset, load_dataset_robot, read_dataset

    ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
    require_sensors(ds, "calibrate")
    robot = load_dataset_robot(ds)
    planes_given = data is not None
    if data is None:
        data = calibration_data(ds, robot, progress=progress, plane_max_points=plane_max_points)
    problem = build_problem(ds, robot, data, options)
    lm = solve_problem(problem, progress=progress, stage="first solve (closed-form start, default noise)")
    values, iterations = lm.values, lm.iterations
    outliers: set = set()
    # a laser scanner's clouds that are not scans first: what follows from them is its consequence
    warnings: list[str] = [off_plane_scan_warning(sensor, off, n)
                           for sensor, (off, n) in sorted(getattr(data, "scans_off_plane", {}).items())]
    warnings += plane_source_warnings(plane_max_points, planes_given, ds, data.planes)
    warnings += ground_choice_warnings(data)

    def resolve(opts, excluded, stage, start=None):
        nonlocal problem, values, iterations
        # warm start from the last solution (or the caller's prediction of the new optimum): the
        # graph differs only in noise or left-out measurements
        problem = build_problem(ds, robot, data, opts, exclude=frozenset(excluded),
                                initial=values if start is None else start)
        lm = solve_problem(problem, progress=progress, stage=stage)
        values = lm.values
        iterations += lm.iterations
        noise_stats.clear()  # read at the previous solution

    noise_stats: dict = {}  # the variance components at the current solution and options

    def estimate_noise(opts):
        # variance-component estimation under the Huber loss (outliers are down-weighted)
        for _ in range(VCE_ROUNDS):
            u = noise_update(opts, problem, values)
            noise_stats.update(u.stats)
            if not u.changed:
                break
            opts, step = u.options, u.step
            # start at the variance estimation's linear solution with the new weights: the
            # re-weighted optimum to first order (fewer LM iterations)
            resolve(opts, outliers, "noise re-estimated", start=None if step is None else values.retract(step))
        return opts

    per_sensor: dict = {}
    for m in problem.plane_factors.values():
        per_sensor[m[1]] = per_sensor.get(m[1], 0) + 1

    def leave_out_outliers(opts, *, screen: bool) -> None:
        # data snooping: leave out the worst measurements (within 10x of the worst chi-square),
        # solve again, repeat until every measurement passes; one gross outlier left in biases the
        # estimate enough to make good stations fail the test
        nonlocal outliers
        for _ in range(MAX_OUTLIER_ROUNDS):
            bad, stats = _outlier_measurements(problem, values, opts)
            if not bad:
                break
            worst = max(stats[m] for m in bad)
            new = {m for m in bad if stats[m] >= 0.1 * worst}
            over = [sn for sn in per_sensor
                    if sum(1 for m in outliers | new if m[1] == sn) > MAX_OUTLIER_SHARE * per_sensor[sn]]
            if over:
                if not screen:
                    warnings.append(
                        f"more than {MAX_OUTLIER_SHARE:.0%} of the measurements of {', '.join(over)} fail the "
                        "chi-square test: the model does not fit these data (see graphcal diagnose); none more "
                        "were left out")
                break
            outliers |= new
            stage = "screened at the default noise" if screen else "left out"
            resolve(opts, outliers, f"{len(outliers)} outlier measurement(s) {stage}")

    if options.robust and options.estimate_noise:
        # gross outliers out before the noise is learned: left in, the variance components absorb
        # them (measured: two stations with another station's clouds learned a contact noise of
        # 11 mm and hid both); at the default noise the screen may also take good measurements,
        # which are tested again below with the learned noise
        leave_out_outliers(options, screen=True)
    if options.estimate_noise:
        options = estimate_noise(options)
    if options.robust:
        screened = frozenset(outliers)
        if screened and options.estimate_noise:
            back = _passing_again(ds, robot, data, options, problem, values, screened)
            if back:
                outliers -= back
                resolve(options, outliers, f"{len(back)} screened measurement(s) put back (they pass with the "
                                           "learned noise)")
        leave_out_outliers(options, screen=False)
        if outliers != screened and options.estimate_noise:
            options = estimate_noise(options)
    result = _result(ds, robot, data, problem, values, outliers, iterations, options)
    warnings += implausible_leg_data_warnings(data, robot, options)
    if options.estimate_noise:
        if not noise_stats:  # the rounds ran out (or outliers were left out) after the last update
            noise_stats.update(noise_update(options, problem, values, converge=False).stats)
        groups, noise_warnings = noise_groups_report(noise_stats, options)
        warnings += noise_warnings
        result = dataclasses.replace(result, noise_groups=groups)
    else:
        from graphcal.calibration.noise_check import given_noise_check

        sensors, groups, noise_warnings = given_noise_check(problem, values, options, result.sensors)
        warnings += noise_warnings
        result = dataclasses.replace(result, sensors=sensors, noise_groups=groups)
    if warnings:
        result = dataclasses.replace(result, warnings=tuple(warnings) + result.warnings)
    return result


#: a learned stance-foot noise beyond these is not a robot's encoders and feet but wrong data
#: (measured: one knee column of the wrong sign on a user's hexapod gave contact 9.2-14.9 mm and
#: feet 21.7-22.9 mm off a common ground, clean data 0.1-1.0 mm; the 20 mm of contact before missed it)
PLAUSIBLE_JOINT_SIGMA_RAD = float(np.radians(2.0))
PLAUSIBLE_CONTACT_SIGMA_M = 0.008
#: planted feet further than this off one ground plane: wrong data, or ground rougher than this
#: (then ``--ground-roughness-mm``; Chai's big bumpiness is 10 mm RMS)
PLAUSIBLE_GROUND_SIGMA_M = 0.015
#: a controller that misses its set body pose by more than this: a quaternion in x, y, z, w order,
#: another frame or other units in the body_* columns (measured: xyzw order 6.8 deg / 68 mm)
PLAUSIBLE_COMMANDED_SIGMA_RAD = float(np.radians(5.0))
PLAUSIBLE_COMMANDED_SIGMA_M = 0.05


def implausible_leg_data_warnings(data: CalibrationData, robot, options: CalibrationOptions) -> list[str]:
    """Warnings that the joint angles cannot be what they claim: angles outside the URDF's limits
    (``graphcal validate`` lists them), and a learned stance-foot noise beyond
    :data:`PLAUSIBLE_JOINT_SIGMA_RAD` / :data:`PLAUSIBLE_CONTACT_SIGMA_M` (measured: angles in
    degrees gave 41 deg / 402 mm, two joint columns swapped on one leg 7.2 deg / 44 mm; a simulated
    0.3 deg flex gave 0.29 deg / 1.0 mm)."""
    out = []
    bad_stations, example = 0, None
    for st in data.stations:
        hit = None
        for foot, q in st.q_by_foot.items():
            leg = robot.legs[foot]
            outside = leg.outside_limits(q)
            if outside.any():
                j = int(np.argmax(outside))
                hit = (leg.joint_names[j], float(q[j]), float(leg.lower[j]), float(leg.upper[j]))
                break
        if hit is not None:
            bad_stations += 1
            example = example or (st.station, *hit)
    if bad_stations:
        s, j, q, lo, hi = example
        out.append(f"{bad_stations} of {len(data.stations)} stations have joint angles outside the URDF's limits "
                   f"(station {s}: q_{j} = {q:.4g} rad, limits [{lo:.4g}, {hi:.4g}]): joint angles must be radians, "
                   "with the URDF's joint names and signs (graphcal validate lists them)")
    rough = options.ground_unevenness_m > 0  # --ground-roughness-mm: the feet may sit on bumps
    if options.estimate_noise and (options.sigma_joint_rad > PLAUSIBLE_JOINT_SIGMA_RAD
                                   or options.sigma_contact_m > PLAUSIBLE_CONTACT_SIGMA_M
                                   or (options.sigma_ground_m > PLAUSIBLE_GROUND_SIGMA_M and not rough)):
        out.append(f"the stance feet fit their kinematics implausibly badly (noise learned: joints "
                   f"{np.degrees(options.sigma_joint_rad):.3g} deg, contact {1e3 * options.sigma_contact_m:.3g} mm, "
                   f"feet {1e3 * options.sigma_ground_m:.3g} mm off one ground plane): joint angles in degrees, joint "
                   "columns swapped or of the wrong sign, feet not planted, foot frames that are not the contact "
                   "points, or a robot model that is not this robot's (ground rougher than "
                   f"{1e3 * PLAUSIBLE_GROUND_SIGMA_M:.0f} mm: --ground-roughness-mm); with that noise the legs carry "
                   "almost no weight in the estimate")
    if options.estimate_noise and data.stations and (options.sigma_commanded_rad > PLAUSIBLE_COMMANDED_SIGMA_RAD
                                                     or options.sigma_commanded_m > PLAUSIBLE_COMMANDED_SIGMA_M):
        out.append(f"the commanded body poses (stations.csv body_*) miss the pose the legs and the IMU give by "
                   f"{np.degrees(options.sigma_commanded_rad):.3g} deg / {1e3 * options.sigma_commanded_m:.3g} mm "
                   "(noise learned): a quaternion in x, y, z, w order (the contract's is w, x, y, z), another frame "
                   "than T_world_body, or millimetres")
    return out


VCE_ROUNDS = 8
#: iterations of the variance components on one linearisation, and their stopping tolerance
VCE_INNER_ITERATIONS = 60
VCE_INNER_TOLERANCE = 1e-3
#: stop once every scale is within this of 1
VCE_TOLERANCE = 0.02
MAX_OUTLIER_ROUNDS = 10
#: at most this share of a sensor's measurements is left out as outliers; beyond it the model, not
#: the data, is wrong and calibrate says so instead of discarding the data
MAX_OUTLIER_SHARE = 0.2
#: a group's sigma is re-estimated only with at least this much redundancy (dof), and this share
#: of its rows: below it the residuals say little about the noise (e.g. the planes, whose errors the
#: body poses can absorb almost entirely)
VCE_MIN_REDUNDANCY = 3.0
VCE_MIN_REDUNDANCY_SHARE = 0.05
#: bounds on a re-estimated sigma relative to its default, and absolute floors (SI)
VCE_SCALE_BOUNDS = (0.02, 50.0)
VCE_FLOOR = {"sigma_joint_rad": 1e-6, "sigma_contact_m": 1e-6, "sigma_ground_m": 1e-6, "sigma_imu_rad": 1e-5,
             "sigma_commanded_rad": 1e-5, "sigma_commanded_m": 5e-5}


#: option fields scaled by each noise group's variance component
_GROUP_FIELDS = {"stance_foot/joint": ("sigma_joint_rad",), "stance_foot/contact": ("sigma_contact_m",),
                 "foot_on_ground": ("sigma_ground_m",), "imu": ("sigma_imu_rad",),
                 "commanded": ("sigma_commanded_rad", "sigma_commanded_m")}


class NoiseUpdate(NamedTuple):
    """One variance-component update at a solution (:func:`noise_update`)."""

    #: options with every eligible group's sigma multiplied by its converged scale
    options: CalibrationOptions
    #: False once every eligible scale is within ``VCE_TOLERANCE`` of 1 (a scale held at its bound
    #: is no change)
    changed: bool
    #: the linear step from the solution with the new weights (None on the large-graph path)
    step: "gtsam.VectorValues | None"
    #: group -> :class:`~graphcal.calibration.noise_estimation.GroupVariance` at the solution with
    #: the options given (the statistics a report on the noise model reads)
    stats: dict


def _vce_eligible(v) -> bool:
    """Whether a group's residuals carry enough redundancy for its sigma to be re-estimated."""
    return v.redundancy >= max(VCE_MIN_REDUNDANCY, VCE_MIN_REDUNDANCY_SHARE * v.rows)


def noise_update(options: CalibrationOptions, problem: CalibrationProblem, values, *,
                 converge: bool = True) -> NoiseUpdate:
    """Every noise group's sigma multiplied by its variance-component scale
    (noise_estimation.py) at ``values``. ``converge``: iterate the scales to their fixed point on
    the graph linearised at ``values``
    (:func:`~graphcal.calibration.noise_estimation.converged_scales`); False: one update."""
    import dataclasses

    from graphcal.calibration.noise_estimation import converged_scales

    bounds = {g: (max(VCE_SCALE_BOUNDS[0], *(VCE_FLOOR[n] / getattr(options, n) for n in names)), VCE_SCALE_BOUNDS[1])
              for g, names in _GROUP_FIELDS.items()}

    def changes(stats: dict) -> bool:
        # a scale held at its bound (a sigma at its floor) is no change
        return any(abs(float(np.clip(v.scale, *bounds.get(g, VCE_SCALE_BOUNDS))) - 1.0) > VCE_TOLERANCE
                   for g, v in stats.items() if _vce_eligible(v))

    # converging, a first update that changes nothing ends the call: calibrate then keeps its noise
    # and reads only the statistics (with converge=False the one update is returned as it is)
    first, scale, step = converged_scales(problem.graph, values, problem.factor_groups, problem.factor_components,
                                          eligible=_vce_eligible, bounds=bounds, tolerance=VCE_INNER_TOLERANCE,
                                          max_iterations=VCE_INNER_ITERATIONS if converge else 1,
                                          settled=(lambda stats: not changes(stats)) if converge else None)
    changed = changes(first)
    update = {}
    for group, names in _GROUP_FIELDS.items():
        if group in scale:
            for name in names:
                update[name] = max(getattr(options, name) * scale[group], VCE_FLOOR[name])
    planes = dict(options.plane_sigma_scales)
    for group, s in scale.items():
        if group.startswith("plane:"):
            sensor = group.split(":", 1)[1]
            planes[sensor] = planes.get(sensor, 1.0) * s
    update["plane_sigma_scales"] = tuple(sorted(planes.items()))
    return NoiseUpdate(dataclasses.replace(options, **update), changed, step, first)


def rescaled_options(options: CalibrationOptions, problem: CalibrationProblem, values, *,
                     converge: bool = True) -> tuple[CalibrationOptions, bool, "gtsam.VectorValues | None"]:
    """(options, changed, step) of :func:`noise_update`."""
    u = noise_update(options, problem, values, converge=converge)
    return u.options, u.changed, u.step


#: a held group whose residuals are this improbable under its sigma (chi-square upper tail) makes
#: calibrate warn that the covariance may be too small
NOISE_TOO_SMALL_P = 0.01


#: a learned plane noise scale above this makes calibrate warn (measured: 0.86-1.01 on flat simulated
#: floors, 1.7-18 on Chai's little bumpiness, 3 mm RMS, docs/calibration.md)
PLANE_SCALE_WARN = 1.5


def noise_groups_report(stats: dict, options: CalibrationOptions, *,
                        given: bool = False) -> tuple[tuple[NoiseGroupEstimate, ...], list[str]]:
    """How each noise group's sigma was set, from the variance-component statistics ``stats`` at
    the final solution with the final ``options`` (:class:`NoiseUpdate` ``stats``), and a warning
    for every group whose residuals say its sigma is too small (chi-square upper tail below
    :data:`NOISE_TOO_SMALL_P`) but which the estimation could not correct (too few dof, or the
    rounds ran out): then the reported covariance may be too small.

    A group held with residuals *below* its sigma (``data_scale`` < 1, e.g. the feet's height
    above a perfectly flat simulated floor: 6 rows, under 3 dof) only makes the covariance
    conservative; it is reported, not warned about (docs/calibration.md measures its effect). A
    learned plane noise scale above :data:`PLANE_SCALE_WARN` is warned about: it is what uneven
    ground looks like to this model (and a sensor noisier than its noise model).

    ``given``: the noise was not learned (``--noise-from``, or the defaults): every group's status
    is ``given``, and nothing is warned about here: one group's residuals above its sigma does not
    make the covariance too small when others are conservative (the defaults' planes point to
    x1.2-x3.2 while the incremental mean NEES was 5.99 over 40 simulated sessions);
    :func:`~graphcal.calibration.noise_check.given_noise_check` scales and warns per sensor."""
    from graphcal import stats as chi2_dist

    fields_of = dict(_GROUP_FIELDS)
    out, warnings = [], []
    for key, v in sorted(stats.items()):
        if key in fields_of:
            names = fields_of[key]
            fields = tuple((n, float(getattr(options, n))) for n in names)
        elif key.startswith("plane:"):
            sensor = key.split(":", 1)[1]
            names = ()
            fields = ((f"plane_scale:{sensor}", float(options.plane_scale(sensor))),)
        else:  # not a group whose sigma calibrate re-estimates
            continue
        dof = float(v.redundancy)
        scale = float(v.scale)
        # chi2 / dof = scale^2 for a single group; for one component of a sum, Helmert's theta = scale^2
        # times its dof is the same test to first order
        p_high = float(chi2_dist.sf(scale * scale * dof, dof)) if dof > 1e-9 else float("nan")
        at_floor = bool(names) and all(getattr(options, n) <= VCE_FLOOR[n] * (1 + 1e-9) for n in names)
        if given:
            status = "given"
        elif not _vce_eligible(v):
            status = "too few dof"
        elif abs(scale - 1.0) <= VCE_TOLERANCE:
            status = "learned"
        elif at_floor and scale < 1.0:
            status = "at floor"
        else:
            status = "not converged"
        out.append(NoiseGroupEstimate(key, fields, status, dof, int(v.rows), scale, p_high,
                                      tuple(getattr(v, "shared_with", ()))))
        if given:
            continue
        if key.startswith("plane:") and fields[0][1] > PLANE_SCALE_WARN:
            warnings.append(
                f"{key.split(':', 1)[1]}: the planes scatter {fields[0][1]:.2g} times more than the point noise of "
                "their fits predicts (learned plane noise scale): the sensor is noisier than its noise model, "
                "or the ground is not one plane (bumps: give --ground-roughness-mm; an offset per session or a "
                "tilted floor: graphcal diagnose). On uneven ground the reported covariance is too small: the "
                "scale treats the unevenness as independent noise per station")
        # only residuals above their sigma make the covariance too small (with ~0 dof the chi-square
        # puts all its mass at 0 and any positive statistic has a tiny p: 1 station gave 'residuals
        # 0.058 times its sigma ... may be too small')
        if status != "learned" and scale > 1.0 and p_high < NOISE_TOO_SMALL_P:
            warnings.append(
                f"noise group {key} ({status}, {dof:.1f} dof): its residuals are {scale:.2g} times its sigma "
                f"(chi-square p = {p_high:.2g}); the reported covariance may be too small")
    return tuple(out), warnings


def _result(ds, robot, data, problem: CalibrationProblem, values, outliers: set, iterations: int,
            options: CalibrationOptions) -> CalibrationResult:
    from graphcal.solvers.covariance import body_axis_sigmas, marginal_covariances, unobservable_directions

    keys = list(problem.sensor_keys.values()) + [k for k, _ in problem.leg_keys.values()]
    covs = marginal_covariances(problem.graph, values, keys)
    sensors, warnings = {}, []
    for name, key in problem.sensor_keys.items():
        T = from_gtsam_pose(values.atPose3(key))
        cov = np.asarray(covs[key])
        T_cad, sig_m, sig_rad = problem.sensor_priors[name]
        cov_prior, held = extrinsic_prior_for_observability(sig_m, sig_rad)
        s_rot, s_xyz, corr, _ = body_axis_sigmas(T, cov)
        unobs = tuple(unobservable_directions(T, cov, cov_prior))
        warnings += [f"{name}: {u}" for u in unobs + held]
        conflict = prior_conflict(T, T_cad, sig_m, sig_rad)
        if conflict:
            warnings.append(f"{name}: {conflict}")
        ids = [st.station for st in data.stations]
        sensors[name] = SensorEstimate(
            name=name, type=ds.sensors[name].type, T_body_sensor=T, covariance=cov, T_body_sensor_prior=T_cad,
            sigma_rot_deg=np.asarray(s_rot), sigma_xyz_mm=np.asarray(s_xyz), correlation=np.asarray(corr),
            unobservable=unobs, segments=(ExtrinsicSegment(min(ids), max(ids), T, cov),),
        )
    legs = {}
    for foot, (key, param) in problem.leg_keys.items():
        legs[foot] = LegEstimate(foot, tuple(param.names), np.asarray(values.atVector(key)),
                                 np.sqrt(np.clip(np.diag(covs[key]), 0.0, None)))
    T_world_body = {st: from_gtsam_pose(values.atPose3(k)) for st, k in problem.station_keys.items()}
    residuals = _residuals(data, problem, values, T_world_body, sensors, outliers)
    warnings += flipped_normal_warnings(residuals)
    after = [r for r in residuals if not r.outlier]
    normal_rms = float(np.sqrt(np.mean([r.angle_after_deg**2 for r in after]))) if after else float("nan")
    dist_rms = float(np.sqrt(np.mean([r.distance_after_mm**2 for r in after]))) if after else float("nan")
    return CalibrationResult(
        dataset=str(ds.root) if ds.root is not None else "",
        robot_urdf_xml=robot.urdf_xml,
        robot_name=str(robot.name),
        base_frame=robot.base_frame,
        sensors=sensors,
        legs=legs,
        outliers=tuple(sorted({m[0] for m in outliers})),
        residuals=tuple(residuals),
        normal_rms_deg=normal_rms,
        distance_rms_mm=dist_rms,
        T_world_body=T_world_body,
        solver="batch",
        iterations=iterations,
        warnings=tuple(warnings),
        noise=noise_summary(options, problem),
    )


#: A CAD prior further from the estimate than this many of its own sigmas is reported as wrong.
PRIOR_CONFLICT_SIGMAS = 5.0
#: an estimate this far from its CAD prior, whatever the prior's sigma, points to data in the wrong
#: frame (an audit's planes in the body frame with a 60 deg / 500 mm prior: 137 deg / 395 mm off, no word)
FRAME_MISTAKE_DEG = 30.0
FRAME_MISTAKE_M = 0.25


def prior_conflict(T_body_sensor: np.ndarray, T_prior: np.ndarray, sigma_m: float, sigma_rad: float) -> str:
    """A sentence when the CAD prior (4x4, with its sigma in m and rad from dataset.yaml) is further
    from the calibrated extrinsic than :data:`PRIOR_CONFLICT_SIGMAS` of its own sigma, in rotation
    angle or in translation distance; empty otherwise. The data then outweighed a prior that said
    otherwise: either the prior is wrong or its sigma is too small (and it pulled the estimate)."""
    from graphcal.geometry import rotation_angle_between

    angle = float(rotation_angle_between(T_body_sensor[:3, :3], T_prior[:3, :3]))
    dist = float(np.linalg.norm(T_body_sensor[:3, 3] - T_prior[:3, 3]))
    # a zero sigma holds that part at the CAD value (a note says so): what is left of it is rounding
    k_rot = angle / sigma_rad if sigma_rad > 0 else 0.0
    k_xyz = dist / sigma_m if sigma_m > 0 else 0.0
    frames = angle > np.radians(FRAME_MISTAKE_DEG) or dist > FRAME_MISTAKE_M
    hint = ("; a difference this large is seldom a mounting error: are the planes (planes.csv) and clouds in the "
            "sensor frame, not the body or world frame, and is the prior T_body_sensor, not its inverse? (planes "
            "in the body frame make the data fit a sensor at the body origin)")
    if max(k_rot, k_xyz) <= PRIOR_CONFLICT_SIGMAS:
        if not frames:
            return ""
        return (f"the calibrated pose is {np.degrees(angle):.1f} deg and {1e3 * dist:.0f} mm from the CAD prior in "
                f"dataset.yaml ({max(k_rot, k_xyz):.1f} times its sigma, which allows it)" + hint)
    return (f"the CAD prior in dataset.yaml is {np.degrees(angle):.1f} deg and {1e3 * dist:.0f} mm from the "
            f"calibrated pose, {max(k_rot, k_xyz):.0f} times its stated sigma ({np.degrees(sigma_rad):.3g} deg, "
            f"{1e3 * sigma_m:.3g} mm): the prior is wrong or its sigma too small (a tight wrong prior pulls "
            "the estimate; widen sigma_rpy_deg / sigma_mm or correct the prior)" + (hint if frames else ""))


def flipped_normal_warnings(residuals) -> list[str]:
    """A warning per sensor most of whose planes are answered at more than 90 deg: their normals point
    away from the sensor, against the contract (n from the plane towards the sensor, d >= 0). The
    plane factor does not use the normal's sign, so the estimate stands, but the residual statistics
    read ~180 deg and the exporter has a sign error (an audit's flipped normals went unsaid)."""
    out = []
    for sensor in dict.fromkeys(r.sensor for r in residuals):
        rows = [r for r in residuals if r.sensor == sensor and not r.outlier and np.isfinite(r.angle_after_deg)]
        flipped = sum(1 for r in rows if r.angle_after_deg > 90.0)
        if rows and flipped > len(rows) / 2:
            out.append(f"{sensor}: {flipped} of {len(rows)} plane normals point away from the sensor (answered at "
                       "~180 deg): the contract's n points from the plane towards the sensor with d >= 0; the "
                       "estimate does not depend on that sign, but the residual angles do and the plane exporter "
                       "has a sign error")
    return out


def noise_summary(options: CalibrationOptions, problem: CalibrationProblem) -> dict:
    """The noise model of the final solve, SI units (what ``--noise-from`` reads back)."""
    from graphcal.calibration.noise_file import NOISE_KEYS, PLANE_SCALE_PREFIX

    out = {name: float(getattr(options, name)) for name in NOISE_KEYS}
    for sensor in problem.sensor_keys:
        out[f"{PLANE_SCALE_PREFIX}{sensor}"] = options.plane_scale(sensor)
    return out


def _residuals(data, problem, values, T_world_body, sensors, outliers) -> list[StationResidual]:
    from graphcal.solvers.batch import whitened_errors

    index_of = {m: i for i, m in problem.plane_factors.items()}
    out = []
    for (station, sensor), p in sorted(data.planes.items()):
        if sensor not in sensors:
            continue
        T_cad = problem.sensor_priors[sensor][0]
        a0, d0 = predicted_plane_errors(problem.initial_body[station], T_cad, p.n, p.d)
        a1, d1 = predicted_plane_errors(T_world_body[station], sensors[sensor].T_body_sensor, p.n, p.d)
        i = index_of.get((station, sensor))
        chi2 = float(whitened_errors(problem.graph, values, [i])[0]) if i is not None else float("nan")
        out.append(StationResidual(station, sensor, a0, d0, a1, d1, chi2, (station, sensor) in outliers))
    return out
