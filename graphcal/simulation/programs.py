"""Station programs: the sequences of commanded body poses a calibration session asks the robot to hold.

A program returns :class:`StationCommand` rows: the session (stance) label and the commanded pose
of the body relative to the session's stance frame (x forward, z up, origin on the ground under the
body at the start of the session). Heights are absolute (m above the ground).

* ``chai2015``: the 52 set poses of Chai et al. 2015, Table A1. Chai's ground frame has y up; we map
  it to ours (z up) with x -> x, y -> z, z -> -y, so their rotation gamma' about X_G is our roll,
  beta' about Z_G is our pitch with the sign flipped, alpha' about Y_G is our yaw, and p_y' is the
  body height. For a robot of another size, heights are scaled by (default height / 0.6825 m).
* ``labecki2012``: our reading of Łabęcki & Belter 2012, Fig. 3 (44 samples): stage 1 tilts about
  their y_R (our x, roll) while pitching down (looking down at sample 11), stage 2 tilts about their
  x_R (our pitch) and ends looking up (sample 34 is the highest). x, y, yaw and height constant.
* ``random``: random coverage, roll/pitch uniform within +-15 deg, yaw +-10 deg, height +-10 %,
  x/y +-3 cm, over several sessions (stances); a pose the robot cannot take within its joint
  limits is drawn again (``reachable``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import pose_from_xyz_rpy

PROGRAMS = ("chai2015", "labecki2012", "random")
#: the random program draws a pose the robot cannot take within its joint limits again, at most
#: this many times
RANDOM_REDRAWS = 50

# Chai et al. 2015, Table A1: (alpha', beta', gamma') in degrees, p_y' in mm (p_x' = p_z' = 0).
CHAI2015_TABLE_A1 = (
    (0, 2, 20, 615), (0, 8, 18, 619), (0, 11, 16, 623), (0, 13, 14, 627), (0, 15, 12, 631),
    (0, 17, 10, 635), (0, 19, 8, 639), (0, 19, 6, 643), (0, 19, 4, 647), (0, 20, 2, 651),
    (0, -2, -20, 617), (0, -8, -18, 621), (0, -11, -16, 625), (0, -13, -14, 629), (0, -15, -12, 633),
    (0, -17, -10, 637), (0, -19, -8, 641), (0, -19, -6, 645), (0, -19, -4, 649), (0, -20, -2, 653),
    (0, 3, 19, 690), (0, 9, 17, 694), (0, 12, 15, 698), (0, 15, 13, 698), (0, 17, 11, 694),
    (0, 17, 9, 690), (0, 17, 7, 686), (0, 18, 5, 682), (0, 18, 3, 678), (0, 19, 1, 674),
    (0, -3, -19, 692), (0, -9, -17, 696), (0, -12, -15, 700), (0, -15, -13, 696), (0, -17, -11, 692),
    (0, -17, -9, 688), (0, -17, -7, 684), (0, -18, -5, 680), (0, -18, -3, 676), (0, -19, -1, 672),
    (0, 1, 13, 730), (0, 7, 11, 734), (0, 9, 9, 738), (0, 11, 7, 742), (0, 11, 5, 746),
    (0, 12, 3, 749), (0, -1, -13, 732), (0, -7, -11, 736), (0, -9, -9, 740), (0, -11, -7, 744),
    (0, -11, -5, 748), (0, -12, -3, 750),
)
CHAI2015_REFERENCE_HEIGHT_M = 0.6825  # the middle of Table A1's height range


@dataclass(frozen=True)
class StationCommand:
    """One station: ``station`` id, ``session`` label, and the commanded pose ``T_stance_body`` (4x4)
    of the body in the session's stance frame (m, rad)."""

    station: int
    session: str
    T_stance_body: np.ndarray


def chai2015_pose(alpha_deg: float, beta_deg: float, gamma_deg: float, p_y_mm: float, *, height_scale: float = 1.0) -> np.ndarray:
    """One row of Chai's Table A1 as T_stance_body in our z-up frames (see the module docstring)."""
    roll = np.radians(gamma_deg)
    pitch = -np.radians(beta_deg)
    yaw = np.radians(alpha_deg)
    return pose_from_xyz_rpy([0.0, 0.0, p_y_mm / 1000.0 * height_scale], [roll, pitch, yaw])


def station_program(
    name: str,
    *,
    default_height_m: float,
    n_stations: int | None = None,
    n_sessions: int = 1,
    seed: int = 0,
    tilt_scale: float = 1.0,
    reachable=None,
) -> list[StationCommand]:
    """The commanded poses of a program.

    Args:
        name: one of :data:`PROGRAMS`.
        default_height_m: the robot's nominal standing height (m); heights scale with it.
        n_stations: number of stations (``random`` only; default 60).
        n_sessions: the stations are split into this many sessions (stances), in order.
        seed: random seed (``random`` only).
        tilt_scale: multiplies every commanded roll/pitch (for small robots whose legs reach less).
        reachable: ``T_stance_body (4x4) -> bool``, whether the robot can take a pose within its
            joint limits (``random`` only: a pose it cannot take is drawn again, up to
            :data:`RANDOM_REDRAWS` times, then kept).
    """
    if name not in PROGRAMS:
        from graphcal.simulation.walking import WALKING_PROGRAMS

        raise GraphcalError(f"unknown program {name!r}; expected a station program ({', '.join(PROGRAMS)}), a walk "
                            f"({', '.join(WALKING_PROGRAMS)}) or mocap")
    poses: list[np.ndarray] = []
    if name == "chai2015":
        scale = default_height_m / CHAI2015_REFERENCE_HEIGHT_M
        for a, b, g, py in CHAI2015_TABLE_A1:
            poses.append(chai2015_pose(a, b * tilt_scale, g * tilt_scale, py, height_scale=scale))
    elif name == "labecki2012":
        k = np.arange(44)
        roll = np.zeros(44)
        pitch = np.zeros(44)
        s1 = k < 22  # stage 1: roll sweep 0 -> +10 -> -10 -> 0 while pitching down to 10 deg at sample 11
        roll[s1] = 10.0 * np.sin(2 * np.pi * k[s1] / 22)
        pitch[s1] = 10.0 * np.sin(np.pi * k[s1] / 20)
        s2 = ~s1  # stage 2: pitch from 0 up to -12 deg (looking up) at sample 34, back to 0
        pitch[s2] = -12.0 * np.sin(np.pi * (k[s2] - 22) / 22)
        for r, p in zip(roll, pitch):
            poses.append(pose_from_xyz_rpy([0.0, 0.0, default_height_m], np.radians([r, p, 0.0]) * tilt_scale))
    else:
        rng = np.random.default_rng(seed)
        n = n_stations or 60
        for _ in range(n):
            for _ in range(RANDOM_REDRAWS + 1):
                rpy = np.radians([rng.uniform(-15, 15) * tilt_scale, rng.uniform(-15, 15) * tilt_scale,
                                  rng.uniform(-10, 10)])
                xyz = [rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), default_height_m * rng.uniform(0.9, 1.1)]
                T = pose_from_xyz_rpy(xyz, rpy)
                if reachable is None or reachable(T):
                    break
            poses.append(T)
    if n_sessions < 1 or n_sessions > len(poses):
        raise GraphcalError(f"n_sessions (--sessions) must be between 1 and the number of stations ({len(poses)}, "
                            f"--stations), got {n_sessions}")
    bounds = np.linspace(0, len(poses), n_sessions + 1).round().astype(int)
    out = []
    for s in range(n_sessions):
        for i in range(bounds[s], bounds[s + 1]):
            out.append(StationCommand(station=i + 1, session=f"s{s + 1}", T_stance_body=poses[i]))
    return out
