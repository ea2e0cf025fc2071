"""Incremental (online) recalibration with iSAM2, one station per update, with change detection.

The graph is the batch one (graph.py: the same variables, factors and noise models), fed to gtsam's
iSAM2 in dataset order, each factor exactly once: per station an update A (its body pose, the
variables it uses first, its stance-foot / IMU / commanded-pose factors), the change test
(:mod:`graphcal.calibration.change_detection`) on its planes and scans, then an update B (those
factors). A detected change starts a new extrinsic key for the sensor. :class:`IncrementalCalibrator`
is the dataset-free interface; :func:`calibrate_incremental` feeds the batch problem's own factors
(:func:`station_updates`) and returns a :class:`~graphcal.calibration.result.CalibrationResult`.
Units and frames as in the batch (rad, m; 1-sigma in body axes); no robust loss, no noise learned.

The scheme and why it differs from the batch: docs/incremental.md, "The incremental scheme".
"""

from __future__ import annotations

import logging
from dataclasses import replace
from functools import partial
from typing import Callable, Mapping

import gtsam
import numpy as np

from graphcal.calibration.change_detection import ChangeDetector, Decision, innovation_nis, joint_covariance
from graphcal.calibration.graph import (
    GAUGE_PRIOR_SIGMAS,
    CalibrationOptions,
    CalibrationProblem,
    build_problem,
    extrinsic_prior_for_observability,
    floored_extrinsic_prior,
)
from graphcal.calibration.measurements import CalibrationData, PlaneMeasurement, StationMeasurements, calibration_data, require_sensors
from graphcal.calibration.result import CalibrationResult, ExtrinsicSegment, IncrementalStep, SensorEstimate
from graphcal.errors import GraphcalError
from graphcal.factors.keys import F, S, X
from graphcal.geometry import from_gtsam_pose, to_gtsam_pose

__all__ = ["IncrementalCalibrator", "calibrate_incremental", "station_updates"]

log = logging.getLogger(__name__)


class IncrementalCalibrator:
    """iSAM2 calibration fed one station at a time, with change detection per sensor.

    Args:
        robot: the :class:`~graphcal.models.robot.RobotModel` (legs for the stance-foot factors).
        sensors: sensor name -> ``(T_cad (4, 4), sigma_m, sigma_rad)``: the CAD prior of each
            extrinsic (``CalibrationProblem.sensor_priors`` has this form).
        options: noise models and switches (the batch's :class:`CalibrationOptions`).
            ``options.robust`` switches the outlier guard of the change test on (the plane / scan
            factors stay Gaussian: see the module docstring).
        sensor_types: sensor name -> type (``"depth_camera"``...), for the reported estimates.
        sensor_keys: sensor name -> gtsam key of its first extrinsic segment (default ``S(i)`` in
            ``sensors`` order); new segments take the next free ``S`` indices.
        initial_extrinsics: sensor name -> (4, 4) initial value (default: the CAD value). Only a
            linearisation point: iSAM2 relinearises as the data arrive.
        R_body_imu: (3, 3) IMU mounting rotation (its prior with ``options.estimate_imu_mounting``);
            None ignores the accelerometer.
        imu_sigma_rad: sigma of that mounting prior (dataset.yaml's; at least
            ``options.sigma_imu_mounting_rad`` is used, as graph.py does).
        detect_changes: run the change test before fusing each plane / scan.
        window, p_false_alarm, n_tests: the window chi-square test (:class:`ChangeDetector`):
            ``p_false_alarm`` is spread over ``n_tests`` tests (Bonferroni; 1 = per test).
        outlier_guard: hold an individually inconsistent station until the next one decides
            between an outlier and a change (default: ``options.robust``).
        relinearize_threshold, relinearize_skip: iSAM2's relinearisation threshold (tangent units,
            rad and m) and how many updates apart it checks it.
    """

    def __init__(
        self,
        robot,
        sensors: Mapping[str, tuple],
        *,
        options: CalibrationOptions = CalibrationOptions(),
        sensor_types: Mapping[str, str] | None = None,
        sensor_keys: Mapping[str, int] | None = None,
        initial_extrinsics: Mapping[str, np.ndarray] | None = None,
        R_body_imu: np.ndarray | None = np.eye(3),
        imu_sigma_rad: float = 0.0,
        detect_changes: bool = True,
        window: int = 3,
        p_false_alarm: float = 1e-4,
        n_tests: int = 1,
        outlier_guard: bool | None = None,
        relinearize_threshold: float = 1e-2,
        relinearize_skip: int = 1,
    ):
        if not sensors:
            raise GraphcalError("IncrementalCalibrator needs at least one sensor")
        self.robot = robot
        self.options = options
        self._priors = {name: (np.asarray(p[0], dtype=float), float(p[1]), float(p[2])) for name, p in sensors.items()}
        self._types = dict(sensor_types or {})
        keys = dict(sensor_keys) if sensor_keys is not None else {n: S(i) for i, n in enumerate(self._priors)}
        missing = set(self._priors) - set(keys)
        if missing:
            raise GraphcalError(f"sensor_keys lacks {', '.join(sorted(missing))}")
        self._key = {n: int(keys[n]) for n in self._priors}
        self._base_key = dict(self._key)
        self._next_s = max(gtsam.Symbol(k).index() for k in self._key.values()) + 1
        init = dict(initial_extrinsics or {})
        self._init_ext = {n: np.asarray(init.get(n, self._priors[n][0]), dtype=float) for n in self._priors}
        self._R_body_imu = None if R_body_imu is None else np.asarray(R_body_imu, dtype=float)
        self._imu_sigma_rad = float(imu_sigma_rad)
        self.detect_changes = bool(detect_changes)
        self.max_extra_updates = 5
        guard = options.robust if outlier_guard is None else bool(outlier_guard)
        self._detector = {n: ChangeDetector(window=window, p_false_alarm=p_false_alarm, n_tests=n_tests, guard=guard)
                          for n in self._priors}

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(float(relinearize_threshold))
        params.relinearizeSkip = int(relinearize_skip)
        self._isam = gtsam.ISAM2(params)
        # hold the linearisation point alive: pybind11 then passes it to the Python factors by
        # reference instead of copying every Values at every callback (engineering notes)
        self._lp = self._isam.getLinearizationPoint()

        self._dims: dict[int, int] = {}
        self._in_isam: set[int] = set()
        self._foot_index: dict[tuple[str, str], int] = {}
        self._sessions: set[str] = set()
        self._leg_keys: dict = {}
        self._stations: list[int] = []
        self._initial_body: dict[int, np.ndarray] = {}
        self._makers: dict[tuple[int, str], Callable] = {}  # (station, sensor) -> make(s_key) -> factor
        self._isam_index: dict[tuple[int, str], int] = {}  # fused measurement -> iSAM2 factor index
        self._segments: dict[str, list[dict]] = {n: [] for n in self._priors}  # {"key", "stations"}
        self._held: dict[str, int | None] = {n: None for n in self._priors}
        self._outliers: set[tuple[int, str]] = set()
        self._changes: dict[str, list[int]] = {n: [] for n in self._priors}
        self._last_window: dict[str, tuple[float, int]] = {n: (0.0, 0) for n in self._priors}
        self.history: list[IncrementalStep] = []

    # ------------------------------------------------------------------ properties
    @property
    def stations(self) -> tuple[int, ...]:
        """Station ids added so far, in order."""
        return tuple(self._stations)

    @property
    def sensors(self) -> tuple[str, ...]:
        return tuple(self._priors)

    @property
    def isam(self) -> gtsam.ISAM2:
        """The underlying iSAM2 (read-only use)."""
        return self._isam

    def current_key(self, sensor: str) -> int:
        """Key of the sensor's current extrinsic segment."""
        return self._key[sensor]

    # ------------------------------------------------------------------ station factors (online path)
    def _kinematic_body(self, st: StationMeasurements) -> np.ndarray:
        """T_world_body from the stance feet and the commanded pose (graph.py's initial value)."""
        from graphcal.calibration.kinematic_pose import feet_in_body, ground_from_feet, initial_body_pose

        if len(st.q_by_foot) >= 3:
            u, h = ground_from_feet(feet_in_body(self.robot, st.q_by_foot))
            return initial_body_pose(u, h, st.T_world_body_cmd)
        if st.T_world_body_cmd is not None:
            return np.asarray(st.T_world_body_cmd, dtype=float)
        raise GraphcalError(
            f"station {st.station}: fewer than 3 legs with joint angles and no commanded pose; "
            "the body pose cannot be known"
        )

    def _proprioceptive(self, st: StationMeasurements, T0: np.ndarray, sensors_seen) -> tuple:
        """Update A of the online path, built as graph.py builds the batch graph: the station's
        body pose, new feet / legs / IMU mounting / extrinsics with their priors, and its
        stance-foot, IMU and commanded-pose factors (a fresh graph and values)."""
        from graphcal.calibration.graph import imu_mounting_prior, leg_parameter_priors, station_factors
        from graphcal.calibration.kinematic_pose import feet_in_body
        from graphcal.factors.foot_on_ground import foot_on_ground_factor
        from graphcal.factors.keys import M

        o = self.options
        known = self._in_isam
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        x_key = X(st.station)
        values.insert(x_key, to_gtsam_pose(T0))
        if o.legs and not self._leg_keys:
            for foot, key, param, prior in leg_parameter_priors(self.robot, o):
                self._leg_keys[foot] = (key, param)
                values.insert(key, np.zeros(len(param.names)))
                graph.add(prior)
        first_of_session = st.session not in self._sessions
        self._sessions.add(st.session)
        foot_keys = {}
        for foot, q in st.q_by_foot.items():
            fk = (st.session, foot)
            if fk not in self._foot_index:
                j = len(self._foot_index)
                self._foot_index[fk] = j
                p = T0[:3, :3] @ feet_in_body(self.robot, {foot: q})[0] + T0[:3, 3]
                p[2] = 0.0
                values.insert(F(j), p)
                graph.add(foot_on_ground_factor(F(j), o.sigma_ground_m))
            foot_keys[foot] = F(self._foot_index[fk])
        if st.imu_accel is not None and self._R_body_imu is not None and o.estimate_imu_mounting \
                and M(0) not in known and not values.exists(M(0)):
            values.insert(M(0), gtsam.Rot3(self._R_body_imu))
            graph.add(imu_mounting_prior(self._R_body_imu, self._imu_sigma_rad, o))
        for factor, _, _ in station_factors(self.robot, st, x_key, foot_keys, self._leg_keys, o,
                                            R_body_imu=self._R_body_imu):
            graph.add(factor)
        if st.T_world_body_cmd is None and first_of_session:
            graph.add(gtsam.PriorFactorPose3(x_key, to_gtsam_pose(T0), gtsam.noiseModel.Diagonal.Sigmas(GAUGE_PRIOR_SIGMAS)))
        for name in sensors_seen:
            key = self._base_key[name]
            if key in known:
                continue
            T_cad, sig_m, sig_r = self._priors[name]
            values.insert(key, to_gtsam_pose(self._init_ext[name]))
            graph.add(floored_extrinsic_prior(key, T_cad, sig_m, sig_r))
        return graph, values

    def measurement_factor(self, station: int, sensor: str, s_key: int, *, plane: PlaneMeasurement | None = None,
                           points: np.ndarray | None = None, g_key: int | None = None) -> gtsam.NonlinearFactor:
        """The plane (camera) or range-to-plane (laser) factor of one station and sensor on the
        extrinsic key ``s_key``, built by graph.py's builder but always Gaussian: the incremental
        solver gates outliers with the change test instead of a robust loss (module docstring).
        ``g_key``: the session's ground plane variable (uneven ground, cameras only)."""
        from graphcal.calibration.graph import measurement_factor

        return measurement_factor(X(station), s_key, sensor, self.options, plane=plane, points=points, robust=False,
                                  g_key=g_key)

    def add_station(
        self,
        station: StationMeasurements,
        planes: Mapping[str, PlaneMeasurement] | None = None,
        scan_points: Mapping[str, np.ndarray] | None = None,
        *,
        T_world_body_init: np.ndarray | None = None,
    ) -> tuple[IncrementalStep, ...]:
        """Add one station from its measurements (the online path).

        Args:
            station: joint angles, commanded pose, IMU of the station (``station.station`` is its
                id; ids must be unique).
            planes: sensor name -> ground plane seen at this station (cameras).
            scan_points: sensor name -> (M, 3) ground points in the sensor frame (laser scanners).
            T_world_body_init: initial body pose (default: from the stance feet, as graph.py).

        Returns:
            As :meth:`add_factors`.
        """
        sid = int(station.station)
        if sid in self._initial_body:
            raise GraphcalError(f"station {sid} was already added")
        if self.options.ground_unevenness_m > 0 or self.options.ground_unevenness_rad > 0:
            raise GraphcalError("add_station: uneven ground (options.ground_unevenness_*) needs a ground plane per "
                                "session, which this online path does not build; use calibrate_incremental on a "
                                "dataset, or add_factors with the factors of build_problem")
        planes = dict(planes or {})
        scans = dict(scan_points or {})
        unknown = (set(planes) | set(scans)) - set(self._priors)
        if unknown:
            raise GraphcalError(f"station {sid}: measurements of unknown sensor(s) {', '.join(sorted(unknown))}")
        makers = {}
        for name in self._priors:
            if name in planes:
                makers[name] = partial(self._make, sid, name, planes[name], None)
            elif name in scans:
                makers[name] = partial(self._make, sid, name, None, scans[name])
        T0 = np.asarray(T_world_body_init, dtype=float) if T_world_body_init is not None else self._kinematic_body(station)
        graph, values = self._proprioceptive(station, T0, makers)
        return self.add_factors(sid, graph, values, makers, initial_body=T0)

    def _make(self, station, sensor, plane, points, s_key):
        return self.measurement_factor(station, sensor, s_key, plane=plane, points=points)

    # ------------------------------------------------------------------ the update
    def _covariance_of(self, keys) -> np.ndarray:
        return joint_covariance(self._isam, keys, [self._dims[int(k)] for k in keys])

    def add_factors(
        self,
        station: int,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        measurements: Mapping[str, Callable[[int], gtsam.NonlinearFactor]],
        *,
        initial_body: np.ndarray | None = None,
    ) -> tuple[IncrementalStep, ...]:
        """Add one station from ready-made factors (the lower-level path).

        Args:
            station: the station id; its body pose is ``X(station)``.
            factors: update A: every factor of the station except its sensor measurements, and the
                priors of the variables it introduces (extrinsics included: a sensor's key must be
                in ``values`` with its prior the first time the sensor has a measurement).
            values: initial values of exactly the variables this station introduces.
            measurements: sensor name -> ``make(s_key) -> factor``: the station's measurement of
                that sensor on the extrinsic key ``s_key`` (the key of its current segment).
            initial_body: the body pose's initial value (for the "before" residuals; default: from
                ``values``).

        Returns:
            One :class:`IncrementalStep` per sensor that has an extrinsic estimate (sensor order):
            the estimate and body-axis 1-sigma after this station, the window statistic, and
            whether a change was declared here.
        """
        from graphcal.solvers.covariance import body_axis_sigmas

        sid = int(station)
        x_key = X(sid)
        if sid in self._initial_body:
            raise GraphcalError(f"station {sid} was already added")
        unknown = set(measurements) - set(self._priors)
        if unknown:
            raise GraphcalError(f"station {sid}: measurements of unknown sensor(s) {', '.join(sorted(unknown))}")

        # -- update A: variables and proprioceptive factors (fresh graph and values, never re-fed),
        # then empty updates until nothing needs relinearising: the new body pose's initial value
        # can be far off (no commanded pose: yaw and x, y start at 0) and the change test needs its
        # prediction converged, not one Gauss-Newton step from there
        self._isam.update(factors, values)
        for _ in range(self.max_extra_updates):
            if self._isam.update().getVariablesRelinearized() == 0:
                break
        for k, d in values.dims().items():
            self._dims[int(k)] = int(d)
            self._in_isam.add(int(k))
        self._stations.append(sid)
        self._initial_body[sid] = (np.asarray(initial_body, dtype=float) if initial_body is not None
                                   else from_gtsam_pose(values.atPose3(x_key)))
        missing = [n for n in measurements if self._key[n] not in self._in_isam]
        if missing:
            raise GraphcalError(f"station {sid}: the extrinsic of {', '.join(missing)} has no value and prior yet "
                                "(introduce it in this station's factors)")

        # -- change test on each measurement, before it is fused
        decisions: dict[str, Decision] = {}
        built: dict[str, tuple[int, gtsam.NonlinearFactor]] = {}  # the factor tested, fused if its key holds
        for name, make in measurements.items():
            self._makers[(sid, name)] = make
            if not self.detect_changes:
                continue
            if not any(seg["stations"] for seg in self._segments[name]):
                # the sensor's first measurement: nothing measured before it can have changed, and
                # its innovation would be taken against the CAD prior, linearised there (a laser
                # scan's ranges are far from linear over a 5 deg prior error: clean Messor data
                # declared "changed at station 1")
                continue
            key = self._key[name]
            built[name] = (key, make(key))
            # the current estimate of the factor's variables: body pose, extrinsic (and the
            # session's ground plane on uneven ground)
            est = self._isam.calculateEstimate([int(k) for k in built[name][1].keys()])
            nis, dof = innovation_nis(built[name][1], est, self._covariance_of)
            decisions[name] = self._detector[name].test(sid, nis, dof)

        # -- update B: the measurements (a fresh graph; moved factors removed by index)
        graph, new_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        added: list[tuple[int, tuple[int, str]]] = []
        remove: list[int] = []
        changed: set[str] = set()
        for name in measurements:
            dec = decisions.get(name)
            if dec is not None:
                self._last_window[name] = (dec.window_chi2, dec.window_dof)
                if dec.outlier_station is not None:
                    self._outliers.add((dec.outlier_station, name))
                    self._held[name] = None
            action = "accept" if dec is None else dec.action
            if action == "hold":
                self._held[name] = sid
                continue
            if not self._segments[name]:
                self._segments[name].append({"key": self._key[name], "stations": []})
            if action == "change":
                changed.add(name)
                self._start_segment(name, dec, graph, new_values, remove, added)
            key = self._key[name]
            added.append((graph.size(), (sid, name)))
            graph.add(built[name][1] if name in built and built[name][0] == key else measurements[name](key))
            self._segments[name][-1]["stations"].append(sid)
        if graph.size() or remove:
            result = self._isam.update(graph, new_values, remove)
            indices = list(result.getNewFactorsIndices())
            for pos, m in added:
                self._isam_index[m] = int(indices[pos])
            for k, d in new_values.dims().items():
                self._dims[int(k)] = int(d)
                self._in_isam.add(int(k))

        # -- the steps
        steps = []
        for name in self._priors:
            key = self._key[name]
            if key not in self._in_isam:
                continue
            T = from_gtsam_pose(self._isam.calculateEstimatePose3(key))
            cov = np.asarray(self._isam.marginalCovariance(key), dtype=float)
            s_rot, s_xyz, _, _ = body_axis_sigmas(T, cov)
            chi, dof = self._last_window[name]
            steps.append(IncrementalStep(sid, name, T, np.asarray(s_rot), np.asarray(s_xyz), float(chi), int(dof),
                                         name in changed))
        self.history.extend(steps)
        return tuple(steps)

    def _start_segment(self, name: str, dec: Decision, graph, values, remove: list, added: list) -> None:
        """A change of ``name``'s extrinsic at ``dec.change_station``: new key with a loose prior at
        the old estimate; the measurements from the change station on move to it."""

        old = self._key[name]
        new = int(S(self._next_s))
        self._next_s += 1
        T_old = self._isam.calculateEstimatePose3(old)
        _, sig_m, sig_r = self._priors[name]
        values.insert(new, T_old)
        graph.add(floored_extrinsic_prior(new, from_gtsam_pose(T_old), sig_m, sig_r))
        self._key[name] = new
        self._changes[name].append(int(dec.change_station))
        old_seg = self._segments[name][-1]
        new_seg = {"key": new, "stations": []}
        for st in dec.reroute:
            m = (st, name)
            if m in self._isam_index:
                remove.append(self._isam_index.pop(m))
            if st in old_seg["stations"]:
                old_seg["stations"].remove(st)
            if m in self._makers:
                added.append((graph.size(), m))
                graph.add(self._makers[m](new))
                new_seg["stations"].append(st)
        if self._held[name] in dec.reroute:
            self._held[name] = None
        self._segments[name].append(new_seg)
        if not old_seg["stations"]:
            # nothing left on the old key but its prior: drop the empty segment from the report
            self._segments[name].remove(old_seg)

    # ------------------------------------------------------------------ results
    def refine(self, max_updates: int = 20) -> int:
        """Extra iSAM2 updates without new factors until no variable needs relinearising (the
        estimate then equals the batch optimum to within the relinearisation threshold).
        Returns the number of updates made."""
        n = 0
        for n in range(1, max_updates + 1):
            r = self._isam.update()
            if r.getVariablesRelinearized() == 0:
                break
        return n

    def held_stations(self) -> dict[str, int]:
        """sensor -> station held by the outlier guard (not fused, waiting for the next station)."""
        return {n: s for n, s in self._held.items() if s is not None}

    def outliers(self) -> frozenset:
        """(station, sensor) measurements left out as outliers by the outlier guard."""
        return frozenset(self._outliers)

    def change_stations(self, sensor: str) -> tuple[int, ...]:
        """Stations where a change of the sensor's extrinsic was detected (the first station of
        each new segment)."""
        return tuple(self._changes[sensor])

    def segment_keys(self, sensor: str) -> list[tuple[int, tuple[int, ...]]]:
        """[(key, station ids)] of the sensor's extrinsic segments in order."""
        return [(s["key"], tuple(s["stations"])) for s in self._segments[sensor]]

    def sigmas(self, sensor: str) -> tuple[np.ndarray, np.ndarray]:
        """(sigma_rot_deg (3,), sigma_xyz_mm (3,)) of the current segment in body axes."""
        from graphcal.solvers.covariance import body_axis_sigmas

        key = self._key[sensor]
        if key not in self._in_isam:
            return np.full(3, np.inf), np.full(3, np.inf)
        T = from_gtsam_pose(self._isam.calculateEstimatePose3(key))
        s_rot, s_xyz, _, _ = body_axis_sigmas(T, np.asarray(self._isam.marginalCovariance(key)))
        return np.asarray(s_rot), np.asarray(s_xyz)

    def estimate(self, sensor: str) -> SensorEstimate:
        """The sensor's current estimate (last segment), covariance from iSAM2's marginal, its
        earlier segments and the stations where it changed."""
        from graphcal.solvers.covariance import body_axis_sigmas, unobservable_directions

        if sensor not in self._priors:
            raise GraphcalError(f"unknown sensor {sensor!r}; known: {', '.join(self._priors)}")
        key = self._key[sensor]
        if key not in self._in_isam:
            raise GraphcalError(f"sensor {sensor!r} has no measurement yet")
        segs = []
        for s in self._segments[sensor]:
            T_s = from_gtsam_pose(self._isam.calculateEstimatePose3(s["key"]))
            C_s = np.asarray(self._isam.marginalCovariance(s["key"]), dtype=float)
            ids = s["stations"] or [self._stations[-1]]
            segs.append(ExtrinsicSegment(ids[0], ids[-1], T_s, C_s))
        T = from_gtsam_pose(self._isam.calculateEstimatePose3(key))
        cov = np.asarray(self._isam.marginalCovariance(key), dtype=float)
        T_cad, sig_m, sig_r = self._priors[sensor]
        s_rot, s_xyz, corr, _ = body_axis_sigmas(T, cov)
        prior, _ = extrinsic_prior_for_observability(sig_m, sig_r)  # the batch result carries the notes
        return SensorEstimate(
            name=sensor, type=self._types.get(sensor, ""), T_body_sensor=T, covariance=cov, T_body_sensor_prior=T_cad,
            sigma_rot_deg=np.asarray(s_rot), sigma_xyz_mm=np.asarray(s_xyz), correlation=np.asarray(corr),
            unobservable=tuple(unobservable_directions(T, cov, prior)), segments=tuple(segs),
            change_stations=self.change_stations(sensor),
        )

    def problem(self) -> tuple[CalibrationProblem, gtsam.Values]:
        """The graph iSAM2 holds (removed factors left out) as a :class:`CalibrationProblem`, and
        the current estimate: for reports and batch covariances. ``sensor_keys`` are the current
        (last) segments. ``factor_groups`` names the plane / scan factors' group (``plane:<sensor>``)
        only: the other factors came from the caller, with no group attached."""
        factors = self._isam.getFactorsUnsafe()
        graph = gtsam.NonlinearFactorGraph()
        remap = {}
        for i in range(factors.size()):
            f = factors.at(i)
            if f is None:
                continue
            remap[i] = graph.size()
            graph.add(f)
        plane_factors = {remap[i]: m for m, i in self._isam_index.items() if i in remap}
        values = self._isam.calculateEstimate()
        stations = {s: X(s) for s in self._stations}
        ext0 = {n: self._init_ext[n] for n in self._priors if self._key[n] in self._in_isam}
        problem = CalibrationProblem(
            graph=graph, initial=values, sensor_keys={n: self._key[n] for n in ext0},
            sensor_priors={n: self._priors[n] for n in ext0}, station_keys=stations, leg_keys=dict(self._leg_keys),
            plane_factors=plane_factors, initial_body=dict(self._initial_body), initial_extrinsics=ext0,
            factor_groups={i: f"plane:{m[1]}" for i, m in plane_factors.items()},
            excluded=frozenset(self._outliers) | frozenset((s, n) for n, s in self.held_stations().items()),
        )
        return problem, values


def station_updates(problem: CalibrationProblem, data: CalibrationData):
    """Split a built batch problem into one update per station, in dataset order.

    Yields, per station, ``(factors, values, measurements)``: a fresh graph with the factors that
    involve this station's body pose X(i) — and the factors that touch no body pose (extrinsic,
    leg and IMU-mounting priors, foot-on-ground) with the update that first introduces their
    variable —, the initial values of the variables first used here, and sensor name -> index of
    the station's plane / scan factor in ``problem.graph`` (kept apart: the change test looks at
    it before it is fused). Every factor of ``problem.graph`` is yielded exactly once.
    """
    order = {st.station: i for i, st in enumerate(data.stations)}
    x_step = {int(problem.station_keys[s]): i for s, i in order.items() if s in problem.station_keys}
    graph = problem.graph
    n = graph.size()
    step = [None] * n
    intro: dict[int, int] = {}
    for i in range(n):
        keys = [int(k) for k in graph.at(i).keys()]
        xs = [x_step[k] for k in keys if k in x_step]
        if xs:
            step[i] = max(xs)
            for k in keys:
                intro[k] = min(intro.get(k, step[i]), step[i])
    for i in range(n):
        if step[i] is None:
            step[i] = max((intro.get(int(k), 0) for k in graph.at(i).keys()), default=0)
    for k in problem.initial.keys():
        intro.setdefault(int(k), 0)
    by_step: list[list[int]] = [[] for _ in data.stations]
    for i in range(n):
        by_step[step[i]].append(i)
    keys_by_step: list[list[int]] = [[] for _ in data.stations]
    for k, s in intro.items():
        keys_by_step[s].append(k)
    for s in range(len(data.stations)):
        g, v, meas = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        for i in by_step[s]:
            if i in problem.plane_factors:
                meas[problem.plane_factors[i][1]] = i
            else:
                g.add(graph.at(i))
        for k in keys_by_step[s]:
            v.insert(k, _value(problem.initial, k))
        yield g, v, meas


def _value(values: gtsam.Values, key: int):
    """The value of ``key`` in a form ``Values.insert`` accepts (Pose3, Rot3, Point3, OrientedPlane3 or
    Vector)."""
    for read in (values.atPose3, values.atRot3, values.atPoint3, values.atOrientedPlane3, values.atVector):
        try:
            return read(key)
        except RuntimeError:
            continue
    raise GraphcalError(f"cannot read variable {gtsam.DefaultKeyFormatter(key)} of the initial values")


def _batch_or_rebuilt(problem: CalibrationProblem, cal: IncrementalCalibrator, data: CalibrationData, station: int,
                      sensor: str, index: int, s_key: int) -> gtsam.NonlinearFactor:
    """The batch graph's own measurement factor on its own key; rebuilt on a new segment's key
    (on the batch factor's ground plane variable, if it has one: uneven ground)."""
    factor = problem.graph.at(index)
    if s_key == problem.sensor_keys[sensor]:
        return factor
    m = (station, sensor)
    if m in data.planes:
        g_keys = [int(k) for k in factor.keys() if gtsam.Symbol(k).chr() == ord("g")]
        return cal.measurement_factor(station, sensor, s_key, plane=data.planes[m],
                                      g_key=g_keys[0] if g_keys else None)
    return cal.measurement_factor(station, sensor, s_key, points=data.scan_points[m])


def _sigmas_below(cal: IncrementalCalibrator, steps, target_deg: float | None, target_mm: float | None) -> bool:
    """Every sensor has an estimate and all its body-axis sigmas are below the targets."""
    by_sensor = {s.sensor: s for s in steps}
    for name in cal.sensors:
        s = by_sensor.get(name)
        if s is None:
            return False
        if target_deg is not None and not np.all(s.sigma_rot_deg < target_deg):
            return False
        if target_mm is not None and not np.all(s.sigma_xyz_mm < target_mm):
            return False
    return True


def calibrator_for_problem(ds, robot, problem: CalibrationProblem, data: CalibrationData,
                           options: CalibrationOptions, **detector) -> IncrementalCalibrator:
    """The :class:`IncrementalCalibrator` of a dataset's built batch ``problem``: its sensor priors,
    keys and closed-form initial extrinsics, the IMU's mounting prior from dataset.yaml, and the
    change test spread over the dataset's stations (``detector``: ``detect_changes``, ``window``,
    ``p_false_alarm``, ...)."""
    imu = ds.imu.T_body_imu_prior if ds.imu is not None else None
    return IncrementalCalibrator(
        robot, problem.sensor_priors, options=options,
        sensor_types={n: ds.sensors[n].type for n in problem.sensor_keys}, sensor_keys=problem.sensor_keys,
        initial_extrinsics=problem.initial_extrinsics,
        R_body_imu=imu.matrix[:3, :3] if imu is not None else None,
        imu_sigma_rad=imu.sigma_rad if imu is not None else 0.0,
        n_tests=max(1, len(data.stations)), **detector)


def dataset_station_steps(problem: CalibrationProblem, data: CalibrationData, cal: IncrementalCalibrator):
    """Per station in dataset order, what :meth:`IncrementalCalibrator.add_factors` takes:
    ``(station, factors, values, measurement makers)`` (:func:`station_updates`; a measurement is the
    batch graph's own factor, rebuilt on a new segment's key)."""
    for st, (graph_a, values_a, meas) in zip(data.stations, station_updates(problem, data)):
        makers = {name: partial(_batch_or_rebuilt, problem, cal, data, st.station, name, idx)
                  for name, idx in meas.items()}
        yield st, graph_a, values_a, makers


def calibrate_incremental(
    dataset,
    *,
    options: CalibrationOptions = CalibrationOptions(),
    progress: bool = False,
    sigma_target_deg: float | None = None,
    sigma_target_mm: float | None = None,
    window: int = 3,
    p_false_alarm: float = 1e-4,
    detect_changes: bool = True,
    data: CalibrationData | None = None,
    plane_max_points: int | None = None,
    judge: bool = True,
) -> CalibrationResult:
    """Calibrate a dataset incrementally: iSAM2, one station per update in dataset order.

    Args:
        dataset: a dataset folder or a :class:`graphcal.io.dataset.Dataset`.
        options: noise models and switches (as the batch).
        progress: log one line (INFO) per station.
        judge: give the result its adequacy verdict (:func:`judge_incremental`; False: the model's
            covariance, no verdict).
        sigma_target_deg, sigma_target_mm: stop rule: stop adding stations once every sensor's
            1-sigma about every body axis is below ``sigma_target_deg`` and along every body axis
            below ``sigma_target_mm`` (either may be None: not checked). The station where it
            stopped is the last of ``history`` and is named in ``warnings``.
        window, p_false_alarm: change test (change_detection.py): a window of stations, and the
            probability of any false alarm in the run per sensor (Bonferroni over the stations).
        detect_changes: run the change test.
        data: the dataset's measurements when already gathered.
        plane_max_points: as in :func:`graphcal.calibration.calibrate.calibrate`.

    Returns:
        A :class:`CalibrationResult` with ``solver="incremental"``, ``iterations`` = stations
        added, ``history`` = one :class:`IncrementalStep` per station and sensor, and per sensor
        its extrinsic segments and change stations.
    """
    from graphcal.calibration.ground_selection import ground_choice_warnings
    from graphcal.calibration.measurements import plane_source_warnings
    from graphcal.calibration.noise_check import given_noise_check
    from graphcal.calibration.residuals import plane_residuals
    from graphcal.calibration.result import calibration_result
    from graphcal.io.dataset import Dataset, load_dataset_robot, read_dataset
    from graphcal.solvers.covariance import marginal_covariances

    ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
    require_sensors(ds, "calibrate --incremental")
    robot = load_dataset_robot(ds)
    planes_given = data is not None
    if data is None:
        data = calibration_data(ds, robot, progress=progress, plane_max_points=plane_max_points)
    warnings: list[str] = plane_source_warnings(plane_max_points, planes_given, ds, data.planes)
    warnings += ground_choice_warnings(data)
    problem = build_problem(ds, robot, data, replace(options, robust=False))  # Gaussian planes, gated
    cal = calibrator_for_problem(ds, robot, problem, data, options, detect_changes=detect_changes, window=window,
                                 p_false_alarm=p_false_alarm)
    stopped = None
    targets = sigma_target_deg is not None or sigma_target_mm is not None
    for st, graph_a, values_a, makers in dataset_station_steps(problem, data, cal):
        steps = cal.add_factors(st.station, graph_a, values_a, makers, initial_body=problem.initial_body[st.station])
        if progress:
            txt = "; ".join(f"{s.sensor}: rot {np.round(s.sigma_rot_deg, 3).tolist()} deg, "
                            f"xyz {np.round(s.sigma_xyz_mm, 2).tolist()} mm"
                            + (" CHANGE" if s.change_detected else "") for s in steps)
            log.info(f"calibrate --incremental: station {st.station}: {txt}")
        if targets and _sigmas_below(cal, steps, sigma_target_deg, sigma_target_mm):
            stopped = st.station
            break
    cal.refine()
    for name, s in cal.held_stations().items():
        warnings.append(f"{name}: station {s}'s measurement disagreed with the extrinsic and no later station "
                        "confirmed a change; it was left out")
    if stopped is not None:
        n_left = len(data.stations) - len(cal.stations)
        warnings.append(f"stop rule: every sigma below the target after station {stopped} "
                        f"({len(cal.stations)} stations); {n_left} later station(s) not used")
    for name in cal.sensors:
        for c in cal.change_stations(name):
            warnings.append(f"{name}: the extrinsic changed at station {c} (new segment from there on)")

    # -- the result, assembled as the batch's (result.calibration_result) on the graph iSAM2 holds
    inc_problem, values = cal.problem()
    used = set(cal.stations)
    sub = CalibrationData(
        stations=tuple(st for st in data.stations if st.station in used),
        planes={m: p for m, p in data.planes.items() if m[0] in used and m[1] in inc_problem.sensor_keys},
        scan_points={m: p for m, p in data.scan_points.items() if m[0] in used},
        sensor_types=data.sensor_types,
    )
    inc_problem = replace(inc_problem, initial_body={s: problem.initial_body[s] for s in used},
                          leg_keys=dict(problem.leg_keys))
    outliers = set(inc_problem.excluded)
    res = calibration_result(ds, robot, sub, inc_problem, values, outliers, len(cal.stations), options)

    seg_keys = {n: cal.segment_keys(n) for n in res.sensors}
    all_keys = [k for segs in seg_keys.values() for k, _ in segs]
    covs = marginal_covariances(inc_problem.graph, values, all_keys)
    sensors = {}
    residuals = {(r.station, r.sensor): r for r in res.residuals}
    T_world_body = res.T_world_body
    for name, est in res.sensors.items():
        segments = []
        for k, ids in seg_keys[name]:
            T_k = from_gtsam_pose(values.atPose3(k))
            ids = ids or (max(used),)
            segments.append(ExtrinsicSegment(ids[0], ids[-1], T_k, np.asarray(covs[k])))
            if k != inc_problem.sensor_keys[name]:
                # residuals of an earlier segment: against that segment's extrinsic
                part = CalibrationData(sub.stations, {m: p for m, p in sub.planes.items()
                                                      if m[1] == name and m[0] in ids}, {}, sub.sensor_types)
                for r in plane_residuals(part, inc_problem, values, T_world_body,
                                    {name: replace(est, T_body_sensor=T_k)}, outliers):
                    residuals[(r.station, r.sensor)] = r
        sensors[name] = replace(est, segments=tuple(segments), change_stations=cal.change_stations(name))
    # the noise was given, not learned: checked against this run's residuals, the extrinsic covariance
    # scaled up where the planes scatter more than it predicts (noise_check.py)
    sensors, groups, noise_warnings = given_noise_check(inc_problem, values, options, sensors)
    res_list = tuple(sorted(residuals.values(), key=lambda r: (r.station, r.sensor)))
    after = [r for r in res_list if not r.outlier]
    normal_rms = float(np.sqrt(np.mean([r.angle_after_deg**2 for r in after]))) if after else float("nan")
    dist_rms = float(np.sqrt(np.mean([r.distance_after_mm**2 for r in after]))) if after else float("nan")
    result = replace(
        res, sensors=sensors, residuals=res_list, normal_rms_deg=normal_rms, distance_rms_mm=dist_rms,
        solver="incremental", history=tuple(cal.history),
        warnings=tuple(res.warnings) + tuple(warnings) + tuple(noise_warnings), noise_groups=groups,
    )
    if not judge:
        return result
    from graphcal.calibration.calibrate import noise_groups_pointed_to

    changed = any(cal.change_stations(n) for n in res.sensors)
    full = None if changed else batch_problem_at(ds, robot, sub, options, values)
    result = judge_incremental(ds, options, inc_problem, values, result,
                               batch_groups=None if full is None else noise_groups_pointed_to(options, full,
                                                                                               full.initial))
    if full is None:  # a sensor moved: its range scale is not checked (one extrinsic per sensor)
        return result
    from graphcal.calibration.range_observability import range_scale_checks, with_range_scale_checks

    return with_range_scale_checks(result, range_scale_checks(
        ds, full, full.initial, sub, options, (getattr(ds, "extra", None) or {}).get("physical_noise")))


def batch_problem_at(ds, robot, data, options: CalibrationOptions, values):
    """The batch graph of ``data`` under ``options`` at the incremental solution ``values`` (its
    ``initial``), or None when the batch cannot build it there: the graph iSAM2 holds has noise
    groups only for the planes."""
    try:
        return build_problem(ds, robot, data, options, exclude=frozenset(), initial=values)
    except (RuntimeError, KeyError, ValueError):  # a graph the batch cannot build there: planes only
        return None


def judge_incremental(ds, options: CalibrationOptions, problem, values, result, *, batch_groups: tuple = ()):
    """``result`` of the incremental solver with its adequacy verdict (adequacy.py): the given noise
    groups judged against the physical noise at the factor their residuals point to, gross stations
    flagged (not left out: iSAM2 has moved on), and when the model does not fit the robust
    covariance of robust.py governing (the model's scaled by the given noise's misfit plus the jackknife over
    stations; no ``--legs`` solve) and the warning first. Segments other than the last keep the
    model covariance. ``batch_groups``: the full batch graph's noise groups at this solution (judged instead of the planes-only
    groups of ``result`` when given)."""
    from graphcal.calibration.adequacy import adequacy_verdict, gross_stations, group_checks, misfit_warning
    from graphcal.calibration.calibrate import dataset_physical_noise, model_sigmas
    from graphcal.calibration.robust import robust_parts, station_chi2, with_robust_covariance

    physical, sources = dataset_physical_noise(ds, options)
    seen = {m[0] for m in problem.plane_factors.values()}
    gross = gross_stations(station_chi2(problem, values, seen))
    noise_groups = batch_groups or result.noise_groups
    checks = group_checks(noise_groups, physical, sources, model_sigmas(options, noise_groups))
    verdict = adequacy_verdict(checks, gross, legs=options.legs, gross_left_out=False)
    if not verdict.fits:
        extra, scale = robust_parts(problem, values, frozenset(problem.excluded), result, checks, None)
        result = with_robust_covariance(result, extra, scale)
    first = tuple(w for w in (misfit_warning(verdict),) if w)
    return replace(result, adequacy=verdict, warnings=first + result.warnings)
