"""Walks written the way real robots write their logs (issue 42): raw foot-force counts with a
per-foot offset and gain, a stand-up before the walk and a lie-down after it, the IMU off the base
link, a 400 Hz log, and noise levels drawn away from graphcal's defaults -- the simulator's values
never reach a tracker that reads this log, which must learn them (docs/simulation.md, "Real-like
logs"). Every draw comes from the seed; :func:`graphcal.simulation.write.write_real_like` writes one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.simulation.walking import GAITS, WalkingConfig

__all__ = ["RealLikeLog", "real_like_log"]


@dataclass(frozen=True)
class RealLikeLog:
    """A walk's :class:`WalkingConfig` and how its foot forces are written: foot -> (offset counts,
    gain N per count), or None (the robot has no foot-force sensors: joint torques only)."""

    config: WalkingConfig
    force_counts: dict | None


def real_like_log(program: str, seed: int, *, duration_s: float = 25.0, rate_hz: float = 400.0) -> RealLikeLog:
    """A real-like log of a walking program (``trot``, ``walk``, ``tripod-walk``): noise densities
    (gyro 5e-4..2e-3 rad/s/sqrt(Hz), accelerometer 2e-3..8e-3 m/s^2/sqrt(Hz), encoders 0.3..2 mrad,
    bias walks 1..5x the simulator's), the IMU up to 8 cm off the base link (3 cm vertically), a
    1..2 s lie on the belly with a 0.8..1.5 s stand-up and lie-down, counts offset by 0..120 with
    gains 0.05..0.6 N per count."""
    rng = np.random.default_rng([seed, 42])
    u = rng.uniform
    imu = (u(-0.08, 0.08), u(-0.08, 0.08), u(-0.03, 0.03))
    cfg = WalkingConfig(program=program, seed=seed, duration_s=duration_s, rate_hz=rate_hz, cloud_rate_hz=0.0,
                        gyro_noise_density=u(5e-4, 2e-3), accel_noise_density=u(2e-3, 8e-3),
                        gyro_bias_rw=1e-5 * u(1, 5), accel_bias_rw=1e-4 * u(1, 5),
                        encoder_sigma_rad=u(3e-4, 2e-3), force_sigma_n=u(1.0, 5.0), imu_xyz_m=imu,
                        lying_s=u(1.0, 2.0), stand_up_s=u(0.8, 1.5), lie_down_s=u(0.8, 1.5))
    counts = None
    if GAITS[program].force_sensors:
        counts = {f: (float(u(0.0, 120.0)), float(u(0.05, 0.6))) for f in _feet(GAITS[program].robot)}
    return RealLikeLog(cfg, counts)


def _feet(robot: str) -> tuple:
    from graphcal.models.builtin import builtin_info

    return tuple(builtin_info(robot).feet)
