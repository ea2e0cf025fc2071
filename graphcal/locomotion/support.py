"""Support detection from joint torques (Zhao 2020, Eqs. 4-5 and section 3.1).

Each foot's tip force follows from its leg's joint torques through the leg Jacobian:
``tau = J(q)^T f``  =>  ``f = (J^T)^-1 tau``, with J the position Jacobian of the foot in the body
frame (:func:`graphcal.models.kinematics.leg_jacobian`) and f the force the foot exerts on the
ground, in the body frame (N). The load of a foot is the downward part of that force along the
body's z axis (``-f_z``). Of the two tripods, the one whose loads sum higher carries the robot: it
is in stance (Zhao: "If the sum of support force of group A is larger than group B, it is believed
that group A is in support phase"). A hysteresis (the other tripod must carry ``hysteresis_n``
more before the detection switches) keeps torque noise from flickering the decision during the
short six-foot support.

Any other gait (a quadruped's trot or walk: any set of feet in stance) is read foot by foot: the
load of each foot -- from a foot-force sensor, or from its leg's torques as above -- switches it
into stance above ``on_n`` and out below ``off_n`` (a hysteresis per foot,
:func:`stance_from_loads`), giving a stance mask per sample; the thresholds can be learned per foot
from the loads themselves (:mod:`graphcal.locomotion.contact_detection`).

Everything is vectorised over the samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError

__all__ = ["SupportEstimate", "tip_forces", "detect_support", "support_from_torques", "foot_loads",
           "stance_from_loads"]


@dataclass(frozen=True, eq=False)
class SupportEstimate:
    """Which tripod carries the robot at each sample.

    Attributes:
        group: (N,) int, index into ``groups`` of the tripod in stance.
        groups: the tripods, tuples of foot frame names.
        loads: (N, n_feet) load of each foot (N, downward along body z), ``feet`` order.
        feet: foot frame names of ``loads``' columns.
    """

    group: np.ndarray
    groups: tuple
    loads: np.ndarray
    feet: tuple

    def stance_mask(self) -> np.ndarray:
        """(N, n_feet) bool: foot belongs to the detected stance tripod."""
        out = np.zeros(self.loads.shape, dtype=bool)
        for gi, g in enumerate(self.groups):
            cols = [self.feet.index(f) for f in g]
            out[np.ix_(self.group == gi, cols)] = True
        return out


def tip_forces(leg, q: np.ndarray, tau: np.ndarray, *, jacobian: np.ndarray | None = None) -> np.ndarray:
    """Force (N) the foot exerts on the ground, body frame, from joint angles and torques (Zhao Eq. 5).

    Args:
        leg: :class:`graphcal.models.robot.Leg` with 3 joints (a square Jacobian).
        q: (N, 3) joint angles, rad. tau: (N, 3) joint torques, N m (``leg.joint_names`` order).
        jacobian: (N, 3, 3) the leg Jacobian at q if already computed (body frame, m/rad).

    Returns:
        (N, 3) f with tau = J(q)^T f. Raises GraphcalError for a leg that is not 3-DOF or a
        singular configuration.
    """
    from graphcal.models.kinematics import leg_jacobian

    if leg.n_joints != 3:
        raise GraphcalError(f"support detection needs 3-DOF legs; foot {leg.foot} has {leg.n_joints} joints")
    q = np.atleast_2d(np.asarray(q, dtype=float))
    tau = np.atleast_2d(np.asarray(tau, dtype=float))
    if q.shape != tau.shape:
        raise GraphcalError(f"q and tau of foot {leg.foot} differ in shape: {q.shape} vs {tau.shape}")
    J = leg_jacobian(leg, q) if jacobian is None else np.asarray(jacobian, dtype=float)
    JT = np.swapaxes(J, 1, 2)
    try:
        return np.linalg.solve(JT, tau[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        raise GraphcalError(f"foot {leg.foot}: singular leg Jacobian (a stretched knee?)") from None


def detect_support(loads: np.ndarray, feet, groups, *, hysteresis_n: float = 20.0) -> np.ndarray:
    """(N,) index of the tripod in stance from the foot loads (N, n_feet), with hysteresis (N)."""
    loads = np.asarray(loads, dtype=float)
    cols = [[list(feet).index(f) for f in g] for g in groups]
    if len(groups) != 2:
        raise GraphcalError(f"support detection compares two tripods, got {len(groups)} groups")
    sums = np.stack([loads[:, c].sum(axis=1) for c in cols], axis=1)
    diff = sums[:, 1] - sums[:, 0]
    out = np.empty(len(loads), dtype=np.int64)
    # a switch needs the other tripod to carry more by the hysteresis: a small state machine run
    # over the (few) samples where the decision can change
    current = int(diff[0] > 0) if len(diff) else 0
    flip_to_1 = diff > hysteresis_n
    flip_to_0 = diff < -hysteresis_n
    events = np.flatnonzero(flip_to_1 | flip_to_0)
    start = 0
    for k in events:
        want = 1 if flip_to_1[k] else 0
        if want != current:
            out[start:k] = current
            current, start = want, k
    out[start:] = current
    return out


def support_from_torques(robot, q_by_joint, tau_by_joint, groups, *, hysteresis_n: float = 20.0,
                         jacobians: dict | None = None) -> SupportEstimate:
    """Support detection for a whole timeseries.

    Args:
        robot: :class:`graphcal.models.robot.RobotModel`.
        q_by_joint, tau_by_joint: joint name -> (N,) angles (rad) and torques (N m).
        groups: the two tripods (tuples of foot frame names).
        hysteresis_n: load margin (N) before the detection switches tripods.
        jacobians: foot -> (N, 3, 3) leg Jacobians at q, if already computed.
    """
    feet = tuple(f for g in groups for f in g)
    loads = np.empty((len(next(iter(q_by_joint.values()))), len(feet)))
    for i, f in enumerate(feet):
        leg = robot.leg(f)
        q = np.column_stack([q_by_joint[j] for j in leg.joint_names])
        tau = np.column_stack([tau_by_joint[j] for j in leg.joint_names])
        J = jacobians.get(f) if jacobians else None
        loads[:, i] = -tip_forces(leg, q, tau, jacobian=J)[:, 2]
    return SupportEstimate(detect_support(loads, feet, groups, hysteresis_n=hysteresis_n), tuple(groups), loads, feet)


def foot_loads(robot, q_by_joint, tau_by_joint, feet, *, jacobians: dict | None = None) -> np.ndarray:
    """(N, n_feet) load of each of ``feet`` (N, downward along body z: ``-f_z`` of
    :func:`tip_forces`) from joint angles (rad) and torques (N m), joint name -> (N,)."""
    loads = np.empty((len(next(iter(q_by_joint.values()))), len(feet)))
    for i, f in enumerate(feet):
        leg = robot.leg(f)
        q = np.column_stack([q_by_joint[j] for j in leg.joint_names])
        tau = np.column_stack([tau_by_joint[j] for j in leg.joint_names])
        J = jacobians.get(f) if jacobians else None
        loads[:, i] = -tip_forces(leg, q, tau, jacobian=J)[:, 2]
    return loads


def stance_from_loads(loads: np.ndarray, *, on_n, off_n) -> np.ndarray:
    """(N, n_feet) bool stance mask from foot loads (N, n_feet), a hysteresis per foot: a foot
    enters stance when its load exceeds ``on_n`` and leaves it when the load falls below ``off_n``
    (``off_n <= on_n``); it starts in stance when its first load is above the midpoint. ``on_n``
    and ``off_n`` are numbers or one per foot (n_feet,), in the loads' unit (N, or raw counts with
    thresholds learned from them: :mod:`graphcal.locomotion.contact_detection`)."""
    from graphcal.locomotion.contact_detection import hysteresis_mask

    return hysteresis_mask(loads, on_n, off_n)
