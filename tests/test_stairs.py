"""Tests of graphcal.locomotion.stairs: the stairs model from simulated depth clouds with pose errors.

Data (graphcal.simulation.stairs_clouds): the ``stairs`` terrain (three 130 x 300 mm steps from x = 1.2 m, Zhao
2020), the qingzhui depth camera (Kinect noise sigma_z = 1.425e-3 z^2, quarter resolution) at ten
body poses approaching the stairs, the poses handed to the model perturbed by ~1.7 cm and ~0.5 deg
(1 cm and 0.3 deg per axis). Goal of the issue: tread height and depth within 5 mm of the truth.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from graphcal.errors import GraphcalError
from graphcal.geometry import fit_rigid_transform, transform_points
from graphcal.locomotion.stairs import (
    StairsError,
    StairsModel,
    StairsModelConfig,
    model_stairs,
    stairs_model_from_steps,
    tread_errors,
)
from graphcal.report.stairs_json import stairs_to_json
from graphcal.simulation.stairs_clouds import simulate_stairs_clouds

GOAL_M = 0.005


@pytest.fixture(scope="module")
def seq():
    return simulate_stairs_clouds(seed=2)


@pytest.fixture(scope="module")
def model(seq):
    return model_stairs(seq.clouds_sensor, seq.T_world_sensor_est)


def _misregistration_mm(seq, poses, used) -> float:
    """RMS (mm) over clouds of each cloud's mean vertical offset on the true horizontal surfaces,
    after the best common rigid transform (a common error of the map cancels in heights)."""
    Pt, Pc, lab = [], [], []
    for k in used:
        c = seq.clouds_sensor[k]
        c = c[c[:, 2] <= 2.5]
        Pt.append(transform_points(seq.T_world_sensor_true[k], c))
        Pc.append(transform_points(poses[k], c))
        lab.append(np.full(len(c), k))
    Pt, Pc, lab = np.vstack(Pt), np.vstack(Pc), np.concatenate(lab)
    A = fit_rigid_transform(Pt, Pc)
    dz = (Pc - transform_points(A, Pt))[:, 2]
    horiz = np.min(np.abs(Pt[:, 2, None] - np.array([0.0, 0.13, 0.26, 0.39])), axis=1) < 0.003
    per = [dz[(lab == k) & horiz].mean() for k in used if np.any((lab == k) & horiz)]
    return 1000 * float(np.sqrt(np.mean(np.square(per))))


def test_treads_within_goal(seq, model):
    steps = seq.terrain.stairs
    assert len(model.treads) == 3
    errs = tread_errors(model, steps)
    assert [e.true_index for e in errs] == [0, 1, 2]
    for e in errs:
        assert abs(e.height_error_m) < GOAL_M, e
    complete = [e for e, t in zip(errs, model.treads) if t.depth_complete]
    # the two lower treads have both risers in view; the landing's back edge is never seen
    assert len(complete) == 2 and not model.treads[2].depth_complete
    for e in complete:
        assert abs(e.depth_error_m) < GOAL_M, e
    # the edges come from the riser planes and sit where the (averaged) pose estimate puts them
    assert all(t.edge_from_riser for t in model.treads)
    for e in errs:
        assert abs(e.edge_along_m) < 0.02 and abs(e.edge_height_m) < 0.02, e
    # width: the visible part (the camera sees the lateral ends only far away)
    for t, s in zip(model.treads, steps):
        assert s.width_m - 0.15 < t.width_m < s.width_m + 0.01
    # the stairs frame: walking direction along world +x, up along z, origin under the first nosing
    assert model.walking_direction_world @ np.array([1.0, 0.0, 0.0]) > np.cos(np.radians(1.0))
    assert model.up_world @ np.array([0.0, 0.0, 1.0]) > np.cos(np.radians(1.0))
    assert abs(model.T_world_stairs[0, 3] - steps[0].x_start_m) < 0.02


def test_icp_stitching_removes_the_pose_errors(seq, model):
    assert sum(model.icp_accepted) >= 9
    used = [k for k, a in enumerate(model.icp_accepted) if a]
    before = _misregistration_mm(seq, seq.T_world_sensor_est, used)
    after = _misregistration_mm(seq, model.T_world_sensor_corrected, used)
    assert before > 5.0  # the pose errors would blur the treads by more than the goal
    assert after < 1.0, (before, after)
    # the stitched map keeps the estimate's frame: its common error is the average of the clouds'
    for T_c, T_t in zip(model.T_world_sensor_corrected, seq.T_world_sensor_true):
        assert np.linalg.norm(T_c[:3, 3] - T_t[:3, 3]) < 0.05


def test_without_icp_the_goal_is_missed(seq):
    m = model_stairs(seq.clouds_sensor, seq.T_world_sensor_est, config=StairsModelConfig(icp=False))
    errs = tread_errors(m, seq.terrain.stairs)
    worst = max([abs(e.height_error_m) for e in errs if np.isfinite(e.height_error_m)] + [0.0])
    missing = {0, 1, 2} - {e.true_index for e in errs}
    assert worst > GOAL_M or missing


def test_exact_model_and_json(seq, model):
    exact = stairs_model_from_steps(seq.terrain.stairs)
    errs = tread_errors(exact, seq.terrain.stairs)
    assert all(abs(e.height_error_m) < 1e-12 and abs(e.depth_error_m) < 1e-12 for e in errs)
    d = stairs_to_json(model, tread_errors(model, seq.terrain.stairs))
    text = json.dumps(d)  # plain JSON (NaN-free)
    back = json.loads(text)
    assert len(back["treads"]) == 3
    assert back["max_abs_height_error_m"] < GOAL_M
    assert back["treads"][2]["errors"]["depth_error_m"] is None  # incomplete depth: no error
    assert abs(back["treads"][0]["height_m"] - model.treads[0].height_m) < 1e-12


def test_bad_input_raises(seq):
    c, T = seq.clouds_sensor, seq.T_world_sensor_est
    with pytest.raises(StairsError, match="2 clouds but 1 poses"):
        model_stairs(c[:2], T[:1])
    with pytest.raises(StairsError, match="no clouds"):
        model_stairs([], [])
    with pytest.raises(StairsError, match=r"shape \(N, 3\)"):
        model_stairs([c[0][:, :2]], [T[0]])
    bad = T[0].copy()
    bad[:3, :3] *= 2.0
    with pytest.raises(StairsError, match="not a rigid transform"):
        model_stairs([c[0]], [bad])
    with pytest.raises(StairsError, match="edge_drop_fraction"):
        model_stairs([c[0]], [T[0]], config=StairsModelConfig(edge_drop_fraction=0.6))
    assert issubclass(StairsError, GraphcalError)
    # no points near enough
    with pytest.raises(StairsError, match="only 0 points"):
        model_stairs([c[0] * 10.0], [T[0]])


def test_one_cloud_needs_no_icp(seq):
    # from the first pose the camera sees the floor, all three risers and the treads
    m = model_stairs(seq.clouds_sensor[:1], seq.T_world_sensor_est[:1])
    assert isinstance(m, StairsModel) and m.icp_accepted == (True,)
    errs = tread_errors(m, seq.terrain.stairs)
    assert len(errs) >= 2
    assert all(abs(e.height_error_m) < GOAL_M for e in errs)
