"""Can these data check a sensor's range scale? (issue 27: never a confident wrong answer)

calibrate's model takes every sensor's range (depth) as exact. A range scale ``s`` (measured range
= ``s`` times the true one) reads every plane's distance, or every beam, ``s`` times too long and
moves the extrinsic's translation by ``(s - 1)`` times the sensor's distance to the floor. When
that distance changes over the stations (tilts, heights) the data see the scale: the planes do
not fit, the adequacy verdict says so and the robust covariance's range-scale term covers the
error (robust.py). When it barely changes, scale and translation are one direction to the data:
the planes fit whatever the scale, and the extrinsic's σ, which assume the scale is exact, can be
far too small (the Messor's laser on Łabęcki's program with a 2 % scale: ``model fits``, 7.6 mm
off with σ 0.15-0.72 mm). No verdict can see that; what can be said is how well the data
determine the scale and what a scale error would do.

For each sensor, without a new solve: the final graph with that sensor's plane or scan factors
replaced by their range-scale form (factors/range_scale.py, through graph.py's
:func:`~graphcal.calibration.graph.measurement_factor`), a scale variable at 1 with a loose prior
(:data:`PRIOR_SIGMA`), linearised at the final values (the other sensors' scales stay exact).
From the joint marginal covariance of the extrinsic ``xi`` (6, sensor tangent) and the scale ``c``:

* ``sigma_from_data``: the scale's σ from the data alone, ``(1/C_cc - 1/PRIOR_SIGMA^2)^-1/2``;
* ``d xi / d c = C_xi,c / C_cc``: how the extrinsic moves with the scale, everything else
  re-fitted (independent of the prior), given per 1 % of scale in body axes (mm, deg).

The scale counts as determined when ``sigma_from_data`` is at most the sensor class's
:data:`~graphcal.models.sensors.RANGE_SCALE_CHECK_PCT` (dataset.yaml ``physical_noise:
range_scale_pct`` overrides it for every sensor); otherwise a warning says that these data cannot
check the scale and what a 1 % error would do.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["RangeScaleCheck", "PRIOR_SIGMA", "range_scale_checks", "range_scale_limits", "range_scale_warning",
           "with_range_scale_checks"]

#: prior sigma of the scale variable (measured / true range): loose, so that the data decide; the
#: data-only sigma is read with it taken out
PRIOR_SIGMA = 1.0


@dataclass(frozen=True)
class RangeScaleCheck:
    """What the data say about one sensor's range scale (module docstring).

    Attributes:
        sensor: the sensor's name.
        sigma_from_data: 1-sigma of the scale from the data alone (a fraction: 0.01 is 1 %); inf
            when the data do not determine it at all.
        translation_mm_per_percent: (3,) how far the sensor's origin moves along the body x, y, z
            axes (mm) for a scale 1 % larger, everything else re-fitted.
        rotation_deg_per_percent: (3,) the rotation about the body axes (deg) for it.
        limit_pct: the largest ``sigma_from_data`` (per cent) for which the scale counts as
            determined, and ``limit_from``: where that limit comes from.
    """

    sensor: str
    sigma_from_data: float
    translation_mm_per_percent: np.ndarray
    rotation_deg_per_percent: np.ndarray
    limit_pct: float
    limit_from: str

    @property
    def determined(self) -> bool:
        return bool(np.isfinite(self.sigma_from_data) and 100.0 * self.sigma_from_data <= self.limit_pct)

    @property
    def translation_mm(self) -> float:
        """Length of :attr:`translation_mm_per_percent` (mm per 1 % of scale)."""
        return float(np.linalg.norm(self.translation_mm_per_percent))

    @property
    def rotation_deg(self) -> float:
        """Angle of :attr:`rotation_deg_per_percent` (deg per 1 % of scale)."""
        return float(np.linalg.norm(self.rotation_deg_per_percent))


def range_scale_limits(ds, declared: Mapping | None) -> dict[str, tuple[float, str]]:
    """sensor -> (limit in per cent, where it comes from): dataset.yaml's ``physical_noise:
    range_scale_pct`` when declared (already validated by adequacy.physical_noise), else the
    default of the sensor's type (:data:`~graphcal.models.sensors.RANGE_SCALE_CHECK_PCT`)."""
    from graphcal.models.sensors import sensor_type

    declared = declared if isinstance(declared, Mapping) else {}
    out = {}
    for name, spec in ds.sensors.items():
        if "range_scale_pct" in declared:
            out[name] = (float(declared["range_scale_pct"]), "dataset.yaml physical_noise range_scale_pct")
        else:
            out[name] = (sensor_type(spec.type).range_scale_check_pct,
                         f"default for a {spec.type} (graphcal/models/sensors.py)")
    return out


def _scaled_graph(problem, values, data, options, sensor: str, c_key: int):
    """(graph, values): ``problem``'s graph with ``sensor``'s plane and scan factors in their
    range-scale form on ``c_key`` (at 1, prior 1 +- PRIOR_SIGMA), the rest as it is."""
    import gtsam

    from graphcal.calibration.graph import measurement_factor

    graph = gtsam.NonlinearFactorGraph()
    for i in range(problem.graph.size()):
        f = problem.graph.at(i)
        m = problem.plane_factors.get(i)
        if f is not None and m is not None and m[1] == sensor:
            keys = [int(k) for k in f.keys()]
            g_key = keys[2] if len(keys) > 2 else None
            if m in data.planes:
                f = measurement_factor(keys[0], keys[1], sensor, options, plane=data.planes[m],
                                       robust=options.robust, c_key=c_key, g_key=g_key)
            else:
                f = measurement_factor(keys[0], keys[1], sensor, options, points=data.scan_points[m],
                                       robust=options.robust, c_key=c_key)
        graph.add(f)
    graph.add(gtsam.PriorFactorVector(c_key, np.array([1.0]), gtsam.noiseModel.Isotropic.Sigma(1, PRIOR_SIGMA)))
    ext = gtsam.Values(values)
    ext.insert(c_key, np.array([1.0]))
    return graph, ext


def range_scale_check(problem, values, data, options, sensor: str, limit: tuple[float, str]) -> RangeScaleCheck | None:
    """The :class:`RangeScaleCheck` of one sensor (module docstring), or None when the linearised
    graph cannot be factorised (then the extrinsic itself is not determined and says so).

    Args:
        problem, values: calibrate's final graph and its solution (gtsam.Values).
        data: the :class:`~graphcal.calibration.measurements.CalibrationData` it was built from.
        options: the final :class:`~graphcal.calibration.graph.CalibrationOptions` (learned noise).
        sensor: the sensor's name; limit: (per cent, source) of :func:`range_scale_limits`.
    """
    import gtsam

    from graphcal.factors.keys import C
    from graphcal.geometry import from_gtsam_pose

    s_key = problem.sensor_keys[sensor]
    c_key = C(900 + list(problem.sensor_keys).index(sensor))  # not a key of calibrate's graph
    if values.exists(c_key):
        return None
    graph, ext = _scaled_graph(problem, values, data, options, sensor, c_key)
    try:
        joint = gtsam.Marginals(graph, ext).jointMarginalCovariance([s_key, c_key])
    except RuntimeError:  # an undetermined direction: the extrinsic's own warning says so
        return None
    c_sc = np.asarray(joint.at(s_key, c_key), dtype=float).reshape(6)
    c_cc = float(np.asarray(joint.at(c_key, c_key)).reshape(-1)[0])
    info = 1.0 / c_cc - 1.0 / PRIOR_SIGMA**2
    sigma = float(1.0 / np.sqrt(info)) if info > 0 else float("inf")
    d = c_sc / c_cc  # d xi / d c, sensor tangent [omega (rad), v (m)] per unit of scale
    R = from_gtsam_pose(values.atPose3(s_key))[:3, :3]
    return RangeScaleCheck(sensor, sigma, 1e3 * 0.01 * (R @ d[3:]), np.degrees(0.01 * (R @ d[:3])), *limit)


def range_scale_checks(ds, problem, values, data, options, declared: Mapping | None) -> tuple[RangeScaleCheck, ...]:
    """:func:`range_scale_check` of every sensor of ``problem`` with planes or scans in it.
    ``declared``: dataset.yaml's ``physical_noise:`` mapping (or None)."""
    limits = range_scale_limits(ds, declared)
    seen = {m[1] for m in problem.plane_factors.values()}
    out = []
    for name in problem.sensor_keys:
        if name in seen:
            c = range_scale_check(problem, values, data, options, name, limits[name])
            if c is not None:
                out.append(c)
    return tuple(out)


def range_scale_warning(c: RangeScaleCheck) -> str:
    """The warning of a scale these data do not determine ("" when they do)."""
    if c.determined:
        return ""
    pm = "not at all" if not np.isfinite(c.sigma_from_data) else f"± {100.0 * c.sigma_from_data:.2g} % from them"
    return (f"{c.sensor}: these data do not determine its range scale ({pm}; checked to {c.limit_pct:.2g} %): a "
            f"scale error of 1 % would move its translation by {c.translation_mm:.2g} mm ({c.rotation_deg:.2g} deg); "
            "the sigma assume the range is exact. Vary the distance to the floor over the stations (tilts, "
            "heights) to check it")


def with_range_scale_checks(result, checks: tuple[RangeScaleCheck, ...]):
    """``result`` with each sensor's ``range_scale_check`` set and the warnings of the undetermined
    ones added last (the data's own warnings stay first: a scale is not checked on wrong data;
    calibrate's console prints them with the verdict, commands/calibrate.py)."""
    by = {c.sensor: c for c in checks}
    sensors = {n: dataclasses.replace(s, range_scale_check=by.get(n)) for n, s in result.sensors.items()}
    said = tuple(w for w in (range_scale_warning(c) for c in checks) if w)
    for c in checks:
        log.info(f"calibrate: range scale of {c.sensor}: ±{100.0 * c.sigma_from_data:.3g} % from the data "
                 f"(limit {c.limit_pct:.2g} %); 1 % moves it {c.translation_mm:.3g} mm, {c.rotation_deg:.3g} deg")
    return dataclasses.replace(result, sensors=sensors, warnings=tuple(result.warnings) + said)
