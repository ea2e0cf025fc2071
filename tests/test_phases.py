"""The phases of a log (issue 42 item 4) and the simulator's stand-up and lie-down: a simulated a1
trot and qingzhui tripod walk that start on the belly, stand up, walk, and lie down are segmented
into those phases at the times the simulation put them (tolerances derived below), from forces in
newtons or raw counts with per-foot offsets and gains; a lifted robot is found; the leg-model mask
is off while lying and lifted."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.locomotion.phases import PHASES, PhaseConfig, kinematic_height, phases_of_inputs, scaled_loads, segment_phases
from graphcal.locomotion.track_inputs import inputs_from_walking
from graphcal.simulation.walking import WalkingConfig, simulate_walking

STAND_UP_S = 1.0
LIE_DOWN_S = 1.0
LYING_S = 1.0


@pytest.fixture(scope="module", params=["trot", "tripod-walk"])
def posture_walk(request):
    return simulate_walking(WalkingConfig(program=request.param, duration_s=10.0, rate_hz=400.0, cloud_rate_hz=0.0,
                                          seed=1, stand_up_s=STAND_UP_S, lie_down_s=LIE_DOWN_S, lying_s=LYING_S))


def _truth(sim) -> dict:
    """The simulation's phase times (s): the body rises during [rise0, rise1] (after the legs took
    the load over the first fifth of the stand-up), lowers during [lower0, lower1]; walking from
    the first lift-off to the last touchdown."""
    t = sim.times
    steps = t[~sim.contact.all(axis=1)]
    lower0 = t[-1] - LYING_S - LIE_DOWN_S
    return {"rise0": LYING_S + 0.2 * STAND_UP_S, "rise1": LYING_S + STAND_UP_S, "walk0": steps[0], "walk1": steps[-1],
            "lower0": lower0, "lower1": lower0 + 0.8 * LIE_DOWN_S}


def test_the_stand_up_and_lie_down_are_simulated_consistently(posture_walk):
    sim = posture_walk
    c = sim.config
    z = sim.T_world_body[:, 2, 3]
    t = sim.times
    h_lie = 0.4 * (0.28 if c.program == "trot" else 0.45)
    assert z[0] == pytest.approx(h_lie) and z[-1] == pytest.approx(h_lie)
    assert z[(t > 2.1) & (t < 2.9)] == pytest.approx(0.28 if c.program == "trot" else 0.45, abs=1e-9)
    assert np.allclose(sim.p_world_foot[:, t < 2.9, 2], 0.0, atol=1e-12)  # the feet stay on the ground
    # the legs carry a tenth of the weight on the belly, all of it standing (IMU: still, gravity only)
    weight = c.body_mass_kg * 9.80665
    load = -sim.force_body_foot[:, :, 2].sum(axis=0)
    assert load[t < 0.9] == pytest.approx(0.1 * weight, rel=1e-6)
    assert load[(t > 2.1) & (t < 2.9)] == pytest.approx(weight, rel=1e-6)
    assert np.abs(np.linalg.norm(sim.imu_accel[t < 0.9], axis=1).mean() - 9.80665) < 0.05
    # rising: the specific force exceeds g while the body accelerates up
    k = np.argmax(np.gradient(np.gradient(z, t), t)[t < 2.5])
    assert 1.2 < t[k] < 2.0 and load[k] > 1.05 * weight


def test_stand_up_walk_lie_down_are_segmented_where_simulated(posture_walk):
    """Tolerances: the stand-up is cut where the kinematic height has covered a quarter and three
    quarters of the way from the lying to the standing height; the quintic rise covers them at
    36 % and 64 % of its time, i.e. 0.36 x 0.8 s = 0.29 s inside the rise at each end (the
    lie-down likewise); 0.3 s allowed. Walking starts and ends where a foot's load crosses a quarter
    of its range on a 25-45 ms load ramp: 0.1 s allowed."""
    sim = posture_walk
    tr = _truth(sim)
    ph = phases_of_inputs(inputs_from_walking(sim, clouds=False))
    names = [s.phase for s in ph.segments]
    assert names == ["lying", "standing_up", "standing", "walking", "standing", "lying_down", "lying"]
    seg = {(s.phase, i): s for i, s in enumerate(ph.segments)}
    up, walking, down = seg["standing_up", 1], seg["walking", 3], seg["lying_down", 5]
    assert tr["rise0"] <= up.start_s <= tr["rise0"] + 0.3 and tr["rise1"] - 0.3 <= up.end_s <= tr["rise1"]
    assert walking.start_s == pytest.approx(tr["walk0"], abs=0.1) and walking.end_s == pytest.approx(tr["walk1"], abs=0.1)
    assert tr["lower0"] <= down.start_s <= tr["lower0"] + 0.3 and tr["lower1"] - 0.3 <= down.end_s <= tr["lower1"]
    assert ph.lying_height_m == pytest.approx(sim.T_world_body[0, 2, 3], abs=0.005)
    assert ph.standing_height_m == pytest.approx(sim.T_world_body[len(sim.times) // 2, 2, 3], abs=0.01)
    # the leg model: not while lying
    lying = ph.labels == PHASES.index("lying")
    assert not ph.leg_model_mask[lying].any() and ph.leg_model_mask[~lying].all()
    assert ph.phase_at(0.5) == "lying" and ph.phase_at(tr["walk0"] + 1.0) == "walking"


def test_raw_counts_with_per_foot_offsets_and_gains_give_the_same_phases():
    sim = simulate_walking(WalkingConfig(program="trot", duration_s=10.0, rate_hz=400.0, cloud_rate_hz=0.0, seed=1,
                                         stand_up_s=STAND_UP_S, lie_down_s=LIE_DOWN_S))
    from graphcal.locomotion.plausibility import feet_in_body

    pbf = feet_in_body(sim.robot, sim.q_measured)
    newtons = segment_phases(sim.times, sim.foot_force, pbf)
    gains, offsets = np.array([3.1, 0.9, 10.0, 2.5]), np.array([-40.0, 12.0, 500.0, 0.0])  # one foot reads ~3x less
    counts = np.round(offsets + gains * sim.foot_force)
    raw = segment_phases(sim.times, counts, pbf)
    assert [s.phase for s in raw.segments] == [s.phase for s in newtons.segments]
    assert np.mean(raw.labels != newtons.labels) < 0.002
    assert np.allclose(scaled_loads(counts), scaled_loads(sim.foot_force), atol=0.02)  # 1-count rounding of 0.9 N


def _synthetic(lift: bool):
    """Four feet at 100 Hz: standing 2 s 0.28 m high (30 N a foot), then 2 s with no load and the
    legs hanging 0.30 m (lift) or the belly down at 0.10 m (lift=False), then standing again;
    trotting in between to give each foot its range."""
    t = np.arange(0.0, 8.0, 0.01)
    N = len(t)
    z = np.full(N, 0.28)
    F = np.full((N, 4), 30.0)
    trot = (t >= 6.0)
    pair = (np.floor(t / 0.25) % 2).astype(bool)
    F[trot] = np.where(np.column_stack([pair, ~pair, ~pair, pair])[trot], 0.0, 60.0)
    off = (t >= 2.0) & (t < 4.0)
    F[off] = 0.5
    z[off] = 0.30 if lift else 0.10
    pbf = np.zeros((4, N, 3))
    pbf[:, :, 2] = -z
    return t, F, pbf


def test_a_lifted_robot_and_a_lying_one():
    t, F, pbf = _synthetic(lift=True)
    ph = segment_phases(t, F, pbf)
    assert [(s.phase, round(s.start_s, 2)) for s in ph.segments] == [("standing", 0.0), ("lifted", 2.0),
                                                                      ("standing", 4.0), ("walking", 6.0)]
    assert not ph.leg_model_mask[(t >= 2.0) & (t < 4.0)].any() and ph.leg_model_mask[t < 2.0].all()
    t, F, pbf = _synthetic(lift=False)
    ph = segment_phases(t, F, pbf)
    # dropping 0.18 m in one sample: no stand-up or lie-down stretch (shorter than min_phase_s)
    assert [s.phase for s in ph.segments] == ["standing", "lying", "standing", "walking"]
    assert ph.lying_height_m == pytest.approx(0.10)
    # a short flight (no foot loaded for 0.1 s, legs extended) is walking, not lifted
    t, F, pbf = _synthetic(lift=True)
    F[(t >= 6.5) & (t < 6.6)] = 0.0
    F[(t >= 2.0) & (t < 4.0)] = 30.0
    pbf[:, (t >= 2.0) & (t < 4.0), 2] = -0.28
    ph = segment_phases(t, F, pbf, PhaseConfig())
    assert [s.phase for s in ph.segments] == ["standing", "walking"]


def test_kinematic_height_uses_the_loaded_feet():
    pbf = np.zeros((2, 3, 3))
    pbf[0, :, 2] = -0.3
    pbf[1, :, 2] = -0.2
    h, reach = kinematic_height(pbf, np.array([[True, False], [True, True], [False, False]]))
    assert np.allclose(h, [0.3, 0.25, 0.25]) and np.allclose(reach, 0.25)


def test_a_stairs_climb_is_walking_throughout_not_standing_up_and_lying_down():
    """The simulated hexapod stairs walk (no lying anywhere): the kinematic height dips as the
    stance feet stand on different steps. Each dip was cut as standing up, then lying down (16
    such stretches in 26 s); a height change between upright stretches is no lying down."""
    sim = simulate_walking(WalkingConfig(program="tripod-stairs", rate_hz=200.0, cloud_rate_hz=0.0, seed=0))
    ph = phases_of_inputs(inputs_from_walking(sim))
    names = [s.phase for s in ph.segments]
    assert "standing_up" not in names and "lying_down" not in names and "lying" not in names, ph.segments
    walk = sum(s.end_s - s.start_s for s in ph.segments if s.phase == "walking")
    steps = sim.times[~sim.contact.all(axis=1)]
    assert walk >= 0.95 * (steps[-1] - steps[0]), ph.segments
