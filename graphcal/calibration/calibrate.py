"""``graphcal calibrate``: from a dataset to the pose of every sensor on the body, with covariance.

Batch mode: build the graph (graph.py), solve it with Levenberg–Marquardt driven from Python
(solvers/batch.py) under a Huber loss, list the measurements that fail a chi-square test as outliers
and solve again without them, learn the noise (noise_estimation.py), then read the result with its
marginal covariances (result.py, solvers/covariance.py). Each solve is a plain function of a frozen
:class:`BatchState`. Last, :func:`judge_result` gives the result its adequacy verdict (adequacy.py:
the noise judged against the physical noise, gross stations left out) and, when the model does not
fit, the robust covariance (robust.py); and, for every sensor, whether the data determine its
range scale, which the model takes as exact (range_observability.py).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from graphcal.calibration.graph import CalibrationOptions, CalibrationProblem, build_problem
from graphcal.calibration.ground_selection import ground_choice_warnings
from graphcal.calibration.measurements import CalibrationData, calibration_data, plane_source_warnings, require_sensors
from graphcal.calibration.noise_estimation import VCE_ROUNDS, noise_groups_report, noise_update
from graphcal.calibration.result import CalibrationResult, calibration_result
from graphcal.errors import GraphcalError
from graphcal.io.dataset import off_plane_scan_warning

log = logging.getLogger(__name__)


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
                   values, excluded: frozenset, extensions=None) -> set:
    """The left-out measurements that pass the chi-square test at ``values``, the solution of
    ``problem`` (built without them) under ``options``: each measurement's innovation, whitened by its
    own noise plus the uncertainty of the variables it sees (their joint marginal in ``problem``),
    the test of the change detector (:func:`~graphcal.calibration.change_detection.innovation_nis`).
    Tested against its own noise alone, a good plane fails: the body pose it would have moved is
    far less certain than the plane. ``extensions``: the graph's extension (None: none)."""
    import gtsam

    from graphcal import stats as chi2_dist
    from graphcal.calibration.change_detection import innovation_nis, joint_covariance

    full = build_problem(ds, robot, data, options, extensions=extensions, initial=values)
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


def solve_problem(problem: CalibrationProblem, *, progress: bool = False, stage: str = "solve"):
    """Levenberg–Marquardt on a built problem; returns the solver result. With ``progress`` one line
    per solve is logged (INFO)."""
    from graphcal.solvers.batch import solve_lm

    result = solve_lm(problem.graph, problem.initial)
    if progress:
        log.info(f"calibrate: {stage}: {problem.graph.size()} factors, {result.iterations} LM iterations, "
                 f"error {result.error_initial:.4g} -> {result.error_final:.4g}")
    return result


@dataclass(frozen=True, eq=False)
class BatchInputs:
    """What every solve of one batch calibration reads: the dataset ``ds``, its ``robot``, the
    measurements ``data`` (:class:`CalibrationData`), ``progress`` (one line per solve to stderr)
    and ``extensions``, extra variables of the graph (a
    :class:`~graphcal.calibration.graph.GraphExtension`; None: calibrate's graph)."""

    ds: object
    robot: object
    data: CalibrationData
    progress: bool = False
    extensions: object = None


@dataclass(frozen=True, eq=False)
class BatchState:
    """Where a batch calibration stands after a solve.

    Attributes:
        problem, values: the graph last solved and its solution (gtsam.Values).
        iterations: LM iterations so far, over every solve.
        outliers: the (station, sensor) measurements left out.
        noise_stats: noise group -> variance components at this solution and options (read by
            :func:`estimate_noise`; empty after a new solve, until read again).
    """

    problem: CalibrationProblem
    values: object
    iterations: int
    outliers: frozenset = frozenset()
    noise_stats: dict = field(default_factory=dict)


def resolve(inputs: BatchInputs, state: BatchState, options: CalibrationOptions, stage: str,
            start=None) -> BatchState:
    """The graph built again under ``options`` without ``state.outliers`` and solved, warm started
    from the last solution (or ``start``, the caller's prediction of the new optimum, gtsam.Values):
    the graph differs only in noise or left-out measurements. ``stage`` names the solve in the
    progress line."""
    problem = build_problem(inputs.ds, inputs.robot, inputs.data, options, exclude=frozenset(state.outliers),
                            extensions=inputs.extensions, initial=state.values if start is None else start)
    lm = solve_problem(problem, progress=inputs.progress, stage=stage)
    # the noise statistics were read at the previous solution
    return dataclasses.replace(state, problem=problem, values=lm.values, iterations=state.iterations + lm.iterations,
                               noise_stats={})


def estimate_noise(inputs: BatchInputs, state: BatchState,
                   options: CalibrationOptions) -> tuple[BatchState, CalibrationOptions]:
    """Variance-component estimation under the Huber loss (outliers are down-weighted): up to
    :data:`~graphcal.calibration.noise_estimation.VCE_ROUNDS` updates of the noise, each followed by
    a solve; returns the state and the options with the learned noise."""
    for _ in range(VCE_ROUNDS):
        u = noise_update(options, state.problem, state.values)
        state = dataclasses.replace(state, noise_stats={**state.noise_stats, **u.stats})
        if not u.changed:
            break
        options, step = u.options, u.step
        # start at the variance estimation's linear solution with the new weights: the
        # re-weighted optimum to first order (fewer LM iterations)
        state = resolve(inputs, state, options, "noise re-estimated",
                        start=None if step is None else state.values.retract(step))
    return state, options


def leave_out_outliers(inputs: BatchInputs, state: BatchState, options: CalibrationOptions, per_sensor: dict, *,
                       screen: bool) -> tuple[BatchState, list[str]]:
    """Data snooping: leave out the worst measurements (within 10x of the worst chi-square), solve
    again, repeat until every measurement passes; one gross outlier left in biases the estimate
    enough to make good stations fail the test. At most :data:`MAX_OUTLIER_SHARE` of a sensor's
    measurements (``per_sensor``: sensor -> number of its measurements) are left out; beyond it a
    warning says so, unless ``screen`` (the screen at the default noise). Returns the state and the
    warnings."""
    warnings = []
    for _ in range(MAX_OUTLIER_ROUNDS):
        bad, stats = _outlier_measurements(state.problem, state.values, options)
        if not bad:
            break
        worst = max(stats[m] for m in bad)
        new = {m for m in bad if stats[m] >= 0.1 * worst}
        over = [sn for sn in per_sensor
                if sum(1 for m in state.outliers | new if m[1] == sn) > MAX_OUTLIER_SHARE * per_sensor[sn]]
        if over:
            if not screen:
                warnings.append(
                    f"more than {MAX_OUTLIER_SHARE:.0%} of the measurements of {', '.join(over)} fail the "
                    "chi-square test: the model does not fit these data (see graphcal diagnose); none more "
                    "were left out")
            break
        state = dataclasses.replace(state, outliers=state.outliers | new)
        stage = "screened at the default noise" if screen else "left out"
        state = resolve(inputs, state, options, f"{len(state.outliers)} outlier measurement(s) {stage}")
    return state, warnings


def calibrate(
    dataset,
    *,
    options: CalibrationOptions = CalibrationOptions(),
    progress: bool = False,
    data: CalibrationData | None = None,
    plane_max_points: int | None = None,
    judge: bool = True,
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
        judge: give the result its adequacy verdict (:func:`judge_result`; False: the ``--legs``
            solve inside it).
    """
    from graphcal.io.dataset import Dataset, load_dataset_robot, read_dataset

    ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
    require_sensors(ds, "calibrate")
    robot = load_dataset_robot(ds)
    planes_given = data is not None
    if data is None:
        data = calibration_data(ds, robot, progress=progress, plane_max_points=plane_max_points)
    inputs = BatchInputs(ds, robot, data, progress)
    # a laser scanner's clouds that are not scans first: what follows from them is its consequence
    warnings: list[str] = [off_plane_scan_warning(sensor, off, n)
                           for sensor, (off, n) in sorted(getattr(data, "scans_off_plane", {}).items())]
    warnings += plane_source_warnings(plane_max_points, planes_given, ds, data.planes)
    warnings += ground_choice_warnings(data)
    state, final_options, more = solve_batch(inputs, options)
    result = read_result(inputs, state, final_options, warnings + more)
    if judge:
        result = judge_result(inputs, state, final_options, result, warnings + more, base_options=options)
    return result


def solve_batch(inputs: BatchInputs, options: CalibrationOptions) -> tuple[BatchState, CalibrationOptions, list[str]]:
    """The batch solves of :func:`calibrate` on ``inputs`` from ``options``: first solve, outliers
    screened at the default noise, noise learned, screened measurements put back when they pass,
    outliers left out, noise learned again. Returns the final state, the final options (learned
    noise) and the warnings of the outlier rounds."""
    ds, robot, data, progress = inputs.ds, inputs.robot, inputs.data, inputs.progress
    problem = build_problem(ds, robot, data, options, extensions=inputs.extensions)
    lm = solve_problem(problem, progress=progress, stage="first solve (closed-form start, default noise)")
    state = BatchState(problem, lm.values, lm.iterations)
    warnings: list[str] = []
    per_sensor: dict = {}
    for m in problem.plane_factors.values():
        per_sensor[m[1]] = per_sensor.get(m[1], 0) + 1

    if options.robust and options.estimate_noise:
        # gross outliers out before the noise is learned: left in, the variance components absorb
        # them (measured: two stations with another station's clouds learned a contact noise of
        # 11 mm and hid both); at the default noise the screen may also take good measurements,
        # which are tested again below with the learned noise
        state, _ = leave_out_outliers(inputs, state, options, per_sensor, screen=True)
    if options.estimate_noise:
        state, options = estimate_noise(inputs, state, options)
    if options.robust:
        screened = state.outliers
        if screened and options.estimate_noise:
            back = _passing_again(ds, robot, data, options, state.problem, state.values, screened,
                                  extensions=inputs.extensions)
            if back:
                state = dataclasses.replace(state, outliers=state.outliers - back)
                state = resolve(inputs, state, options, f"{len(back)} screened measurement(s) put back (they pass "
                                                        "with the learned noise)")
        state, more = leave_out_outliers(inputs, state, options, per_sensor, screen=False)
        warnings += more
        if state.outliers != screened and options.estimate_noise:
            state, options = estimate_noise(inputs, state, options)
    return state, options, warnings


def read_result(inputs: BatchInputs, state: BatchState, options: CalibrationOptions,
                warnings: list[str]) -> CalibrationResult:
    """The :class:`CalibrationResult` of the final ``state`` under the final ``options`` (learned
    noise), with its noise groups, and ``warnings`` (the run's so far) put first."""
    data, robot = inputs.data, inputs.robot
    problem, values = state.problem, state.values
    result = calibration_result(inputs.ds, robot, data, problem, values, set(state.outliers), state.iterations,
                                options)
    warnings = list(warnings) + implausible_leg_data_warnings(data, robot, options)
    if options.estimate_noise:
        noise_stats = state.noise_stats
        if not noise_stats:  # the rounds ran out (or outliers were left out) after the last update
            noise_stats = noise_update(options, problem, values, converge=False).stats
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


def judge_result(inputs: BatchInputs, state: BatchState, options: CalibrationOptions, result: CalibrationResult,
                 warnings: list[str], *, base_options: CalibrationOptions) -> CalibrationResult:
    """``result`` with its adequacy verdict (adequacy.py): gross stations left out (their planes
    join the outliers, the graph is solved and the noise learned again), every noise group judged
    against the physical noise, and when the model does not fit the robust covariance governing
    (robust.py) and the warning first. ``base_options``: the caller's options (before the noise was
    learned), from which the ``--legs`` and range-scale solves of the robust covariance start."""
    from graphcal.calibration.adequacy import adequacy_verdict, gross_stations, group_checks, misfit_warning
    from graphcal.calibration.range_observability import range_scale_checks, with_range_scale_checks
    from graphcal.calibration.robust import robust_parts, station_chi2, with_robust_covariance

    physical, sources = dataset_physical_noise(inputs.ds, options)
    seen = {m[0] for m in state.problem.plane_factors.values() if m not in state.outliers}
    gross = gross_stations(station_chi2(state.problem, state.values, seen))
    if gross:
        bad = {m for m in state.problem.plane_factors.values() if m[0] in {g.station for g in gross}}
        state = dataclasses.replace(state, outliers=state.outliers | bad)
        state = resolve(inputs, state, options, f"{len(gross)} gross station(s) left out")
        if options.estimate_noise:
            state, options = estimate_noise(inputs, state, options)
        result = read_result(inputs, state, options, warnings)
    # learned: the groups as learned; given (--noise-from): what the residuals converge to
    noise_groups = result.noise_groups if options.estimate_noise else noise_groups_pointed_to(
        options, state.problem, state.values)
    groups = group_checks(noise_groups, physical, sources,
                          None if options.estimate_noise else model_sigmas(options, noise_groups))
    verdict = adequacy_verdict(groups, gross, legs=options.legs)
    if not verdict.fits:
        legs = None
        if not options.legs and inputs.robot is not None and getattr(inputs.robot, "legs", None) and any(
                st.q_by_foot for st in inputs.data.stations):
            def legs():
                try:
                    return calibrate(inputs.ds, options=dataclasses.replace(base_options, legs=True),
                                     data=inputs.data, judge=False)
                except (GraphcalError, RuntimeError):  # legs not determined by these data
                    return None
        extra, scale = robust_parts(state.problem, state.values, state.outliers, result, groups, legs,
                                    lambda sensors: range_scale_calibration(inputs, base_options, sensors),
                                    lambda at: extrinsic_change_calibration(inputs, base_options, at))
        result = with_robust_covariance(result, extra, scale)
    first = tuple(w for w in (misfit_warning(verdict),) if w)
    result = dataclasses.replace(result, adequacy=verdict, warnings=first + result.warnings)
    return with_range_scale_checks(result, range_scale_checks(
        inputs.ds, state.problem, state.values, inputs.data, options,
        (getattr(inputs.ds, "extra", None) or {}).get("physical_noise")))


#: prior sigma of the range scale (measured / true range) of the robust covariance's range-scale
#: solve: wide enough not to bias any realistic scale (diagnose frees its scale with the same)
RANGE_SCALE_PRIOR_SIGMA = 0.2


def range_scale_calibration(inputs: BatchInputs, base_options: CalibrationOptions, sensors: tuple[str, ...]):
    """The same data calibrated (:func:`solve_batch`, from ``base_options``: outliers and noise
    learned again) with a range scale of each of ``sensors`` (graph.py's
    :class:`~graphcal.calibration.graph.CalibrateExtension`, prior 1 +- :data:`RANGE_SCALE_PRIOR_SIGMA`):
    (its :class:`CalibrationResult`, with the extrinsics' covariances marginal over the scales;
    sensor -> (scale, its 1-sigma)), or None when these data do not determine it. For the robust
    covariance's range-scale term (robust.py)."""
    from graphcal.calibration.graph import CalibrateExtension
    from graphcal.solvers.covariance import marginal_covariances

    log.info(f"calibrate: robust covariance: the same data solved with a range scale of {', '.join(sensors)}")
    ext = CalibrateExtension(range_scale=tuple((s, RANGE_SCALE_PRIOR_SIGMA) for s in sensors))
    ext_inputs = dataclasses.replace(inputs, extensions=ext)
    try:
        state, options, warnings = solve_batch(ext_inputs, base_options)
        result = read_result(ext_inputs, state, options, warnings)
        keys = {s: state.problem.extension_keys[f"range_scale:{s}"] for s in sensors}
        covs = marginal_covariances(state.problem.graph, state.values, list(keys.values()))
    except (GraphcalError, RuntimeError, KeyError):  # the scale not determined by these data
        return None
    scales = {s: (float(state.values.atVector(k)[0]), float(np.sqrt(max(float(np.asarray(covs[k])[0, 0]), 0.0))))
              for s, k in keys.items()}
    return result, scales


def extrinsic_change_calibration(inputs: BatchInputs, base_options: CalibrationOptions, at: dict):
    """The same data calibrated (:func:`solve_batch`, from ``base_options``: outliers and noise
    learned again) with a second extrinsic of each sensor of ``at`` (sensor -> station) from that
    station on (graph.py's :class:`~graphcal.calibration.graph.CalibrateExtension`): sensor ->
    ((T_body_sensor 4x4, its 6x6 covariance) before the station, (T, covariance) from it on), or
    None when these data do not determine them. For the robust covariance's extrinsic-change term
    (robust.py)."""
    from graphcal.calibration.graph import CalibrateExtension
    from graphcal.solvers.covariance import marginal_covariances

    log.info("calibrate: robust covariance: the same data solved with a second extrinsic of "
             + ", ".join(f"{s} from station {k}" for s, k in at.items()))
    ext_inputs = dataclasses.replace(inputs, extensions=CalibrateExtension(extrinsic_segments=tuple(at.items())))
    try:
        state, _, _ = solve_batch(ext_inputs, base_options)
        keys = {s: (state.problem.sensor_keys[s], state.problem.extension_keys[f"segment:{s}:{k}"])
                for s, k in at.items()}
        covs = marginal_covariances(state.problem.graph, state.values, [k for pair in keys.values() for k in pair])
    except (GraphcalError, RuntimeError, KeyError):  # the segments not determined by these data
        return None
    return {s: tuple((np.asarray(state.values.atPose3(k).matrix()), np.asarray(covs[k])) for k in pair)
            for s, pair in keys.items()}


def adequacy_at(ds, options: CalibrationOptions, problem: CalibrationProblem, values, skip: frozenset = frozenset()):
    """The :class:`~graphcal.calibration.adequacy.Adequacy` of a solved graph (``problem`` at
    ``values``, gtsam.Values) under the noise ``options`` it used: every noise group's statistics
    at the solution (one variance-component update), judged against dataset ``ds``'s physical
    noise, except the groups named in ``skip``. For a model other than calibrate's (diagnose's
    extended one); no gross-station test."""
    from graphcal.calibration.adequacy import adequacy_verdict, group_checks

    physical, sources = dataset_physical_noise(ds, options)
    groups = tuple(g for g in noise_groups_pointed_to(options, problem, values) if g.group not in skip)
    return adequacy_verdict(group_checks(groups, physical, sources), legs=options.legs)


def noise_groups_pointed_to(options: CalibrationOptions, problem: CalibrationProblem, values) -> tuple:
    """The noise groups of a solution whose noise was given, not learned: every group's σ set to
    what its variance components converge to on the linearisation at ``values`` (``fields``; the
    ``dof`` of the first update; ``data_scale`` 1). One update of a given model is not enough to
    judge a group by: with calibrate's defaults (joints 5x the simulator's) the planes point to
    x1.2-x3.2 on clean data, as the loose body poses push the residuals onto them."""
    try:
        u = noise_update(options, problem, values, converge=True)
    except (RuntimeError, ValueError):  # a graph the variance components cannot read
        return ()
    groups, _ = noise_groups_report(u.stats, u.options, given=True)
    return tuple(dataclasses.replace(g, data_scale=1.0) for g in groups)


def model_sigmas(options: CalibrationOptions, noise_groups) -> dict[str, float]:
    """field -> the sigma (SI, or a plane scale for ``plane_scale:<sensor>``) ``options`` give every
    field of ``noise_groups``: the noise a solve with given noise used (adequacy.py's ``used``)."""
    out = {}
    for g in noise_groups:
        for name, _ in g.fields:
            if name.startswith("plane_scale:"):
                out[name] = float(options.plane_scale(name.split(":", 1)[1]))
            else:
                out[name] = float(getattr(options, name))
    return out


def dataset_physical_noise(ds, options: CalibrationOptions) -> tuple[dict, dict]:
    """(key -> physical sigma in deg / mm, key -> source) of dataset ``ds``'s ``physical_noise:``
    (defaults where it declares none; the ground at least ``options.ground_unevenness_m``)."""
    from graphcal.calibration.adequacy import physical_noise

    # "dataset.yaml": the dataset's own (calibration.yaml names the dataset), no machine path
    return physical_noise((getattr(ds, "extra", None) or {}).get("physical_noise"),
                          ground_roughness_m=options.ground_unevenness_m, where="dataset.yaml")


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


#: rounds of data snooping (leave out the worst measurements, solve again)
MAX_OUTLIER_ROUNDS = 10
#: at most this share of a sensor's measurements is left out as outliers; beyond it the model, not
#: the data, is wrong and calibrate says so instead of discarding the data
MAX_OUTLIER_SHARE = 0.2
