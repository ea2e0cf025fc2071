"""The noise model of an earlier calibration, read from its ``calibration.yaml``, as options.

``graphcal calibrate --incremental`` cannot learn the noise (variance-component estimation needs
every residual at once) and starts from the defaults of
:class:`~graphcal.calibration.graph.CalibrationOptions`, which are guesses about a robot graphcal
has not seen. A batch calibration of an earlier session of the same robot writes the sigmas it
learned into ``calibration.yaml`` (``noise_model``, SI units); ``--noise-from`` gives them to a
later run. Measured on simulated Octopus sessions whose joints flex by 0.3 deg (3x the default
joint sigma): docs/incremental.md, "Noise from an earlier calibration".

The block must hold every sigma of :data:`NOISE_KEYS` (finite, > 0) and may hold
``plane_scale:<sensor>`` multipliers; a sensor without one keeps its own noise model (scale 1).
With the noise given, nothing is learned (``estimate_noise`` off), in batch as in incremental mode.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from graphcal.calibration.graph import CalibrationOptions
from graphcal.errors import DatasetError

__all__ = ["NOISE_KEYS", "PLANE_SCALE_PREFIX", "noise_from_mismatch", "noise_summary", "options_with_noise_from"]

#: the sigmas of ``noise_model`` (SI units), all required
NOISE_KEYS = ("sigma_joint_rad", "sigma_contact_m", "sigma_ground_m", "sigma_imu_rad",
              "sigma_commanded_rad", "sigma_commanded_m")
#: ``plane_scale:<sensor>``: multiplier of that sensor's plane / scan noise
PLANE_SCALE_PREFIX = "plane_scale:"


#: the smallest sigma a noise file may give (SI): below it the information (1 / sigma^2) overflows
#: the solver (measured: 1e-300 made a planted foot "undetermined"; 1e-20 worked)
MIN_SIGMA = 1e-12


def _positive(path: Path, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < MIN_SIGMA:
        raise DatasetError(path, f"noise_model.{key}", f"a finite number >= {MIN_SIGMA:g} (SI units)", value)
    return float(value)


def options_with_noise_from(path: str | Path, options: CalibrationOptions) -> tuple[CalibrationOptions, tuple[str, ...]]:
    """``options`` with the sigmas of the ``noise_model`` block of an earlier ``calibration.yaml``.

    Args:
        path: a ``calibration.yaml`` written by ``graphcal calibrate`` (format
            ``graphcal-calibration/1``).
        options: the options to start from (switches such as ``legs`` and the ground roughness
            terms are kept).

    Returns:
        ``(options, sensors)``: the options with :data:`NOISE_KEYS` and the plane scales from the
        file, ``estimate_noise`` off and ``scale_to_plane_residuals`` on (noise_check.py), and the
        names of the sensors the file has a plane scale for.

    Raises:
        DatasetError: unreadable or invalid file, no ``noise_model`` block, a missing sigma, a value
            that is not a finite number > 0, or a key that is not a sigma or a plane scale (the
            message names the file and the key).
    """
    from graphcal.io.calibration_yaml import read_calibration_yaml

    path = Path(path)
    doc = read_calibration_yaml(path)
    block = doc.get("noise_model")
    if block is None:
        raise DatasetError(path, "noise_model", "the noise model of the calibration's final solve (written by "
                           "graphcal calibrate)", "missing")
    if not isinstance(block, dict):
        raise DatasetError(path, "noise_model", f"a mapping of {', '.join(NOISE_KEYS)} and plane_scale:<sensor>",
                           type(block).__name__)
    values: dict[str, float] = {}
    scales: dict[str, float] = {}
    for key, value in block.items():
        if key in NOISE_KEYS:
            values[key] = _positive(path, key, value)
        elif isinstance(key, str) and key.startswith(PLANE_SCALE_PREFIX) and len(key) > len(PLANE_SCALE_PREFIX):
            scales[key[len(PLANE_SCALE_PREFIX):]] = _positive(path, key, value)
        else:
            raise DatasetError(path, f"noise_model.{key}", f"one of {', '.join(NOISE_KEYS)} or plane_scale:<sensor>",
                               "an unknown key")
    missing = [k for k in NOISE_KEYS if k not in values]
    if missing:
        raise DatasetError(path, f"noise_model.{missing[0]}", "this key (required)", "missing")
    out = dataclasses.replace(options, estimate_noise=False, scale_to_plane_residuals=True,
                              plane_sigma_scales=tuple(scales.items()), **values)
    return out, tuple(scales)


def noise_from_mismatch(path: str | Path, robot_name: str, sensors) -> tuple[str, ...]:
    """Warnings when the ``calibration.yaml`` at ``path`` is not of this robot and these sensors.

    A noise model is a property of one robot (its encoders, feet, IMU) and its sensors; another
    robot's is a guess like the defaults, but one the output would call learned.

    Args:
        path: the ``calibration.yaml`` given to ``--noise-from`` (already read by
            :func:`options_with_noise_from`).
        robot_name: the dataset's robot (:attr:`graphcal.models.robot.RobotModel.name`).
        sensors: the dataset's sensor names.

    Returns:
        One sentence per mismatch: another robot, no robot recorded (a file written before
        calibration.yaml recorded it), a plane scale of a sensor the dataset does not have.
    """
    from graphcal.io.calibration_yaml import read_calibration_yaml

    path = Path(path)
    doc = read_calibration_yaml(path)
    out = []
    theirs = doc.get("robot")
    if theirs is None:
        out.append(f"{path} records no robot (written by an older graphcal): cannot check that its noise model "
                   f"is of this robot ({robot_name})")
    elif theirs != robot_name:
        out.append(f"{path} is a calibration of the robot {theirs!r}, this dataset's robot is {robot_name!r}: "
                   "its noise model (encoders, feet, IMU) may not fit these data")
    ours = set(sensors)
    for key in doc.get("noise_model") or {}:
        if isinstance(key, str) and key.startswith(PLANE_SCALE_PREFIX) and key[len(PLANE_SCALE_PREFIX):] not in ours:
            out.append(f"{path} has {key}, but this dataset has no sensor {key[len(PLANE_SCALE_PREFIX):]!r} "
                       f"(its sensors: {', '.join(sorted(ours))})")
    return tuple(out)


def noise_summary(options: CalibrationOptions, problem) -> dict:
    """The noise model of the final solve, SI units (what ``--noise-from`` reads back): every sigma
    of :data:`NOISE_KEYS` from ``options`` and the plane scale of every sensor of ``problem`` (a
    :class:`~graphcal.calibration.graph.CalibrationProblem`)."""
    out = {name: float(getattr(options, name)) for name in NOISE_KEYS}
    for sensor in problem.sensor_keys:
        out[f"{PLANE_SCALE_PREFIX}{sensor}"] = options.plane_scale(sensor)
    return out
