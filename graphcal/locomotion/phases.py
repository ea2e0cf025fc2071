"""The phases of a legged log: lying, standing up, standing, walking, lying down, lifted.

A real log rarely starts and ends standing: the robot lies on its belly, stands up, walks, lies
down; someone lifts it. The filter's leg model (the stance feet planted, the body above them by the
leg kinematics) holds only while the robot stands on its feet: on its belly the feet barely touch
and the legs fold, lifted no foot is on the ground. This module segments a log from two signals it
always has (issue 42 item 4):

* **foot loads**, in any unit (N, or a sensor's raw counts with its own offset and gain): each
  foot's load is scaled to its own range, ``u = (load - low) / (high - low)`` with ``low`` and
  ``high`` the ``range_percentiles`` (2nd and 98th) of that foot's signal over the log; the foot is
  *loaded* above ``load_on`` (0.25). While walking a foot swings (u ~ 0) and carries up to all of
  the weight (u ~ 1; a trot's diagonal pair twice its standing load, u ~ 0.5 standing), so a quarter
  of the range separates standing from unloaded for any gain and offset. The range needs the foot
  unloaded somewhere (a swing, lying, lifted): any log with walking has it.
* **the kinematic body height** ``h``: the body origin above the mean of the loaded feet, along the
  body's z axis, from forward kinematics of the joint angles (``-mean z of p_body_foot``; the mean
  of every foot when none is loaded: how far the legs reach down).

Heights: the *standing height* is the 90th percentile of ``h`` over the samples with a loaded foot;
the *lying height* the 2nd percentile of ``h`` over the log, when it is below ``min_lying_ratio``
(0.6) of the standing height (else the log has no lying, and 0.4 of the standing height stands in
for it). A sample is

* ``lying``: ``h`` below ``lying_fraction`` (a tenth) of the way from the lying to the standing
  height;
* ``lifted``: no foot loaded, the legs reaching down at least ``standing_fraction`` (nine
  tenths) of the way, for at least ``lifted_min_s`` (shorter: a trot's flight phase, walking);
* ``standing`` or ``walking``: a foot loaded and ``h`` at least nine tenths of the way up;
  ``walking`` where some foot is loaded while another is not (a step), gaps between steps shorter
  than ``gait_gap_s`` (a double support, a trot's four-foot moments) filled;
* ``standing_up`` / ``lying_down``: in between, rising / falling (the height at the end of the
  stretch against its start), where the stretch touches lying or the log's start or end; a dip
  between upright stretches (a step up the stairs, a crouch) is walking or standing.

Stretches shorter than ``min_phase_s`` join the phase before them. The filter may use the leg model
where :attr:`PhaseResult.leg_model_mask` is True: everywhere but ``lying`` and ``lifted``.

Units: SI (m, s); loads in the log's own unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PHASES", "PhaseConfig", "PhaseSegment", "PhaseResult", "segment_phases", "phases_of_inputs",
           "kinematic_height", "scaled_loads"]

#: the phase names; :attr:`PhaseResult.labels` indexes this tuple
PHASES = ("lying", "standing_up", "standing", "walking", "lying_down", "lifted")
_LYING, _UP, _STAND, _WALK, _DOWN, _LIFTED = range(len(PHASES))
_UPRIGHT = -1  # standing or walking, before the steps are looked at
_BETWEEN = -2  # standing up or lying down, before the direction is looked at


@dataclass(frozen=True)
class PhaseConfig:
    """Settings of :func:`segment_phases` (module docstring).

    Attributes:
        load_on: a foot is loaded above this fraction of its own load range.
        range_percentiles: (low, high) percentiles of a foot's load giving its range.
        lying_fraction, standing_fraction: below the first fraction of the way from the lying to the
            standing height the robot lies; above the second it stands (walks, or is lifted).
        min_lying_ratio: a lying height is recognised when the lowest height (2nd percentile) is
            below this fraction of the standing height.
        gait_gap_s: gaps between steps shorter than this are walking (s).
        lifted_min_s: no foot loaded with the legs extended at least this long is lifted (s).
        min_phase_s: stretches shorter than this join the phase before them (s).
    """

    load_on: float = 0.25
    range_percentiles: tuple = (2.0, 98.0)
    lying_fraction: float = 0.1
    standing_fraction: float = 0.9
    min_lying_ratio: float = 0.6
    gait_gap_s: float = 0.6
    lifted_min_s: float = 0.3
    min_phase_s: float = 0.2


@dataclass(frozen=True)
class PhaseSegment:
    """One phase: its name (:data:`PHASES`) from ``start_s`` to ``end_s`` (s; the next segment's
    start, the last sample's time for the last one)."""

    phase: str
    start_s: float
    end_s: float


@dataclass(frozen=True, eq=False)
class PhaseResult:
    """The segmentation.

    Attributes:
        segments: :class:`PhaseSegment` in time order.
        labels: (N,) int, index into :data:`PHASES` per sample.
        leg_model_mask: (N,) bool, the filter may use the leg model (not lying, not lifted).
        loaded: (N, n_feet) bool, feet loaded (each foot's own range).
        body_height_m: (N,) the kinematic body height h (m).
        standing_height_m: h standing (m); lying_height_m: h lying (m), None when the log has none.
    """

    segments: tuple
    labels: np.ndarray
    leg_model_mask: np.ndarray
    loaded: np.ndarray
    body_height_m: np.ndarray
    standing_height_m: float
    lying_height_m: float | None

    def phase_at(self, t_s: float) -> str:
        """The phase at time ``t_s`` (s)."""
        seg = [s for s in self.segments if s.start_s <= t_s]
        return (seg[-1] if seg else self.segments[0]).phase


def scaled_loads(loads, percentiles=(2.0, 98.0)) -> np.ndarray:
    """(N, n_feet) each foot's load scaled to its own range: 0 at its low percentile, 1 at its
    high one (any unit, any offset); a foot whose range is 0 gives 0."""
    F = np.asarray(loads, dtype=float)
    lo, hi = np.percentile(F, percentiles, axis=0)
    span = hi - lo
    return np.where(span > 0, (F - lo) / np.where(span > 0, span, 1.0), 0.0)


def kinematic_height(p_body_foot, loaded) -> tuple[np.ndarray, np.ndarray]:
    """(h (N,), reach (N,)) m: the body origin above the mean of the loaded feet along the body's z
    axis (every foot where none is loaded), and above the mean of every foot (how far the legs
    reach down). ``p_body_foot`` (n_feet, N, 3) m, ``loaded`` (N, n_feet) bool."""
    z = -np.asarray(p_body_foot, dtype=float)[:, :, 2].T  # (N, n_feet)
    L = np.asarray(loaded, dtype=bool)
    n = L.sum(axis=1)
    reach = z.mean(axis=1)
    h = np.where(n > 0, (z * L).sum(axis=1) / np.maximum(n, 1), reach)
    return h, reach


def _runs(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the runs of equal labels, ends exclusive."""
    cut = np.flatnonzero(np.diff(labels) != 0) + 1
    return np.r_[0, cut], np.r_[cut, len(labels)]


def _close(mask: np.ndarray, t: np.ndarray, gap_s: float) -> np.ndarray:
    """``mask`` with its False gaps shorter than ``gap_s`` between True samples filled."""
    out = mask.copy()
    idx = np.flatnonzero(mask)
    if len(idx) < 2:
        return out
    gaps = np.flatnonzero(np.diff(idx) > 1)
    for g in gaps[(t[idx[gaps + 1]] - t[idx[gaps]]) < gap_s]:
        out[idx[g] : idx[g + 1]] = True
    return out


def _heights(h: np.ndarray, any_loaded: np.ndarray, cfg: PhaseConfig) -> tuple[float, float | None, float]:
    """(standing height, lying height or None, the lying height the thresholds use) m."""
    h_stand = float(np.percentile(h[any_loaded], 90.0)) if any_loaded.any() else float(np.percentile(h, 90.0))
    low = float(np.percentile(h, 2.0))
    h_lie = low if low < cfg.min_lying_ratio * h_stand else None
    return h_stand, h_lie, (h_lie if h_lie is not None else 0.4 * h_stand)


def _raw_labels(t, h, reach, loaded, h_stand, h_ref, cfg: PhaseConfig) -> np.ndarray:
    """Per sample: lying, lifted, upright (standing or walking) or between (rising or lowering)."""
    lie_level = h_ref + cfg.lying_fraction * (h_stand - h_ref)
    stand_level = h_ref + cfg.standing_fraction * (h_stand - h_ref)
    none = ~loaded.any(axis=1)
    lab = np.full(len(t), _BETWEEN)
    lab[h >= stand_level] = _UPRIGHT
    lifted = none & (reach >= stand_level)
    starts, ends = _runs(lifted.astype(np.int8))
    for a, b in zip(starts, ends):
        if lifted[a] and t[b - 1] - t[a] >= cfg.lifted_min_s:
            lab[a:b] = _LIFTED
    lab[(h < lie_level) & (lab != _LIFTED)] = _LYING
    return lab


def _resolve(t, h, lab, loaded, cfg: PhaseConfig) -> np.ndarray:
    """Upright samples as walking (steps, gaps filled) or standing; in-between stretches as
    standing up (rising) or lying down."""
    out = lab.copy()
    upright = lab == _UPRIGHT
    stepping = loaded.any(axis=1) & ~loaded.all(axis=1) & upright
    walking = _close(stepping, t, cfg.gait_gap_s) & upright
    out[upright] = _STAND
    out[walking] = _WALK
    starts, ends = _runs(out)
    for a, b in zip(starts, ends):
        if out[a] != _BETWEEN:
            continue
        if _next_to_lying(out, a, b):
            out[a:b] = _UP if h[b - 1] >= h[a] else _DOWN
        else:  # a dip between upright stretches (a stairs step, a crouch): the robot did not lie
            out[a:b] = _WALK if _stepping_any(loaded[a:b]) else _STAND
    return out


def _stepping_any(loaded: np.ndarray) -> bool:
    """Some sample of ``loaded`` (n, n_feet) has a foot loaded while another is not (a step)."""
    return bool(np.any(loaded.any(axis=1) & ~loaded.all(axis=1)))


def _next_to_lying(lab: np.ndarray, a: int, b: int) -> bool:
    """The stretch ``lab[a:b]`` begins or ends the log, or touches a lying stretch: standing up
    rises from lying (or from before the log), lying down ends in it (or after the log)."""
    return a == 0 or b == len(lab) or lab[a - 1] == _LYING or lab[b] == _LYING


def _merge_short(t: np.ndarray, lab: np.ndarray, min_s: float) -> np.ndarray:
    """Stretches shorter than ``min_s`` take the label before them (the first: the one after)."""
    out = lab.copy()
    while True:
        starts, ends = _runs(out)
        dur = t[ends - 1] - t[starts]
        short = np.flatnonzero(dur < min_s)
        if not len(short) or len(starts) == 1:
            return out
        i = int(short[np.argmin(dur[short])])
        out[starts[i] : ends[i]] = out[starts[i] - 1] if i > 0 else out[ends[i]]


def segment_phases(times, loads, p_body_foot, config: PhaseConfig = PhaseConfig()) -> PhaseResult:
    """The phases of a log (module docstring).

    Args:
        times: (N,) s.
        loads: (N, n_feet) foot loads in any unit (force sensors, raw counts, loads from the joint
            torques, 0/1 contacts).
        p_body_foot: (n_feet, N, 3) m, the feet from forward kinematics of the joint angles (same
            foot order).
        config: thresholds.
    """
    cfg = config
    t = np.asarray(times, dtype=float)
    loaded = scaled_loads(loads, cfg.range_percentiles) > cfg.load_on
    h, reach = kinematic_height(p_body_foot, loaded)
    h_stand, h_lie, h_ref = _heights(h, loaded.any(axis=1), cfg)
    lab = _raw_labels(t, h, reach, loaded, h_stand, h_ref, cfg)
    lab = _merge_short(t, _resolve(t, h, lab, loaded, cfg), cfg.min_phase_s)
    starts, ends = _runs(lab)
    segs = tuple(PhaseSegment(PHASES[int(lab[a])], float(t[a]), float(t[b] if b < len(t) else t[-1]))
                 for a, b in zip(starts, ends))
    mask = (lab != _LYING) & (lab != _LIFTED)
    return PhaseResult(segs, lab, mask, loaded, h, h_stand, h_lie)


def phases_of_inputs(inputs, config: PhaseConfig = PhaseConfig()) -> PhaseResult:
    """:func:`segment_phases` of a :class:`~graphcal.locomotion.track_inputs.TrackInputs`: loads
    from its foot-force columns, else from its joint torques, else its contacts; feet from its
    joint angles and robot model."""
    from graphcal.locomotion.plausibility import feet_in_body
    from graphcal.locomotion.support import foot_loads

    robot = inputs.robot
    if inputs.force is not None:
        loads = np.asarray(inputs.force, dtype=float)
    elif inputs.tau is not None:
        loads = foot_loads(robot, inputs.q, inputs.tau, tuple(robot.feet))
    else:
        loads = np.asarray(inputs.contact, dtype=float)
    p_body_foot = getattr(inputs, "p_body_foot", None)  # measured foot points (a robot given by its feet)
    feet = p_body_foot if p_body_foot is not None else feet_in_body(robot, inputs.q)
    return segment_phases(inputs.times, loads, feet, config)
