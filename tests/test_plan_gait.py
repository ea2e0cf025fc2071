"""``graphcal plan-gait`` on a tracked stairs walk (the qingzhui's ``tripod-stairs`` program: two 130 x
300 mm steps and a landing from x = 1.6 m, a flight down behind it): the footholds against the TRUE
stairs of truth.yaml, the parameters against the planner's limits, gait.yaml's frames and units, the
report's two figures, bad input, and the treads not seen well enough (refused or warned by name).
The helpers of graphcal.planning.climb are checked on the exact model of known stairs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import yaml

from graphcal.cli import main
from graphcal.locomotion.stairs import stairs_model_from_steps
from graphcal.planning.climb import (
    OUTCOMES,
    edge_distances,
    stability_margin,
    stairs_model_from_json,
    swing_edge_clearances,
    tread_trust,
)
from graphcal.planning.gait import GaitConfig, GaitError
from graphcal.report.stairs_json import stairs_to_json
from graphcal.simulation.terrain import Stair

CFG = GaitConfig()


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """A short stairs walk simulated and tracked by the commands (as tests/test_track.py's ``stairs``),
    then planned: (dataset, track dir, plan dir, gait.yaml, exit code, stderr lines)."""
    root = tmp_path_factory.mktemp("plan_gait")
    ds, track, plan = root / "walk", root / "track", root / "plan"
    assert main(["simulate", "--robot", "qingzhui", "--program", "tripod-stairs", "--cloud-rate", "3", "--out",
                 str(ds), "--quiet"]) == 0
    assert main(["track", str(ds), "--out", str(track), "--quiet"]) == 0
    assert main(["plan-gait", str(track), "--out", str(plan), "--quiet"]) == 0
    return ds, track, plan, yaml.safe_load((plan / "gait.yaml").read_text())


def _true_profile(ds):
    """The true stairs of truth.yaml in the side view (x, z): nosings (N, 2) (the upper corner of every
    vertical face, going up and down) and risers (N, 3) (x, z_low, z_high)."""
    steps = sorted((yaml.safe_load((ds / "truth.yaml").read_text())["ground"]["stairs"]), key=lambda s: s["x_start_m"])
    surf = [(-np.inf, steps[0]["x_start_m"], 0.0)] + [
        (s["x_start_m"], s["x_start_m"] + s["depth_m"], s["height_m"]) for s in steps] + [
        (steps[-1]["x_start_m"] + steps[-1]["depth_m"], np.inf, 0.0)]
    nos, ris = [], []
    for (_, b, h0), (a, _, h1) in zip(surf[:-1], surf[1:]):
        assert abs(a - b) < 1e-9  # contiguous steps
        nos.append((b, max(h0, h1)))
        ris.append((b, min(h0, h1), max(h0, h1)))
    return np.array(nos), np.array(ris), steps


def _footholds(doc):
    for st in doc["steps"]:
        for foot, fh in st["footholds"].items():
            yield st, foot, fh


# ----------------------------------------------------------------------------- end to end
def test_footholds_at_least_3_cm_from_every_true_nosing_and_riser(planned):
    """The issue's target, on the plan made from the perceived stairs: every foothold (world frame of
    the estimate) at least 3 cm from every true nosing and riser, standing on a true surface."""
    ds, _, _, doc = planned
    nos, ris, steps = _true_profile(ds)
    n = 0
    for st, foot, fh in _footholds(doc):
        x, _, z = fh["p_world_foot"]
        d_nos = np.hypot(nos[:, 0] - x, nos[:, 1] - z).min()
        d_ris = np.hypot(ris[:, 0] - x, np.clip(z, ris[:, 1], ris[:, 2]) - z).min()
        assert d_nos >= 0.03 and d_ris >= 0.03, (st["step"], foot, d_nos, d_ris)
        on = [s["height_m"] for s in steps if s["x_start_m"] <= x < s["x_start_m"] + s["depth_m"]]
        assert abs(z - (on[0] if on else 0.0)) < 0.015, (st["step"], foot, z)  # not in the air, not in a step
        n += 1
    assert n >= 24  # 8+ steps of three feet
    s = doc["summary"]
    assert s["outcome"] in OUTCOMES
    assert s["feet_on_top"] >= 3  # the front tripod reaches the landing
    assert s["min_nosing_distance_m"] >= CFG.near_zone_m - 1e-6 and s["min_riser_distance_m"] >= CFG.far_zone_m - 1e-6


def test_swing_clears_every_true_nosing_by_2_cm(planned):
    """The shin's axis (the leg following the planned path by IK) stays at least 2 cm + the shin's
    radius from every TRUE nosing (sharp edges: no edge radius) in every planned swing."""
    from graphcal.models.robot import load_robot

    ds, _, _, doc = planned
    _, _, steps = _true_profile(ds)
    up = [s for i, s in enumerate(steps) if all(s["height_m"] > t["height_m"] for t in steps[:i])]
    truth = stairs_model_from_steps([Stair(**s) for s in up])
    robot = load_robot(model="qingzhui")
    worst = np.inf
    T0 = np.array(doc["start"]["T_world_body"])
    for st in doc["steps"]:
        T1 = np.array(st["body"]["T_world_body_end"])
        for foot, fh in st["footholds"].items():
            c = swing_edge_clearances(robot, foot, T0, T1, fh["p_world_lift"], fh["p_world_foot"], st["step_height_m"],
                                      truth)
            assert np.all(np.isfinite(c))
            worst = min(worst, float(c.min()) + CFG.edge_radius_m)
        T0 = T1
    assert worst >= 0.02, worst


def test_parameters_within_the_planners_limits(planned):
    _, _, _, doc = planned
    groups = doc["start"]["groups"]
    assert doc["config"]["gait"]["max_step_length_m"] == CFG.max_step_length_m
    prev = None
    lengths = []
    for st in doc["steps"]:
        L, H = st["step_length_m"], st["step_height_m"]
        assert 0.0 <= L <= CFG.max_step_length_m and 0.0 <= H <= CFG.max_step_height_m
        assert any(lo - 1e-9 <= L <= hi + 1e-9 for lo, hi in st["step_length_intervals_m"])
        assert any(lo - 1e-9 <= H <= hi + 1e-9 for lo, hi in st["step_height_intervals_m"])
        lengths.append(L)
        assert st["swing_feet"] == groups[st["swing_tripod"]]
        assert st["swing_tripod"] != prev  # tripods alternate
        prev = st["swing_tripod"]
        assert abs(st["body"]["pitch_deg"]) <= 30.0 + 1e-6
        assert 0.3 < st["body"]["height_m"] < 0.5
        assert st["stability_margin_m"] > 0.0
        assert st["planning_ms"] > 0.0  # recorded; its budget is a bench matter, not a test's
        for fh in st["footholds"].values():
            assert fh["swing"]["min_clearance_over_nosings_m"] >= 0.0 and fh["swing"]["collides"] is False
    # the non-advancing steps of a stall (two in a row, one per tripod) are not part of the plan
    assert not any(a < 0.02 and b < 0.02 for a, b in zip(lengths[:-1], lengths[1:]))
    # the parameters adapt: the step height rises to climb, and is low on the floor
    heights = [st["step_height_m"] for st in doc["steps"]]
    assert max(heights) >= 0.04 and min(heights) <= 0.02


def test_gait_yaml_frames_units_and_both_frames_agree(planned):
    _, _, plan, doc = planned
    text = (plan / "gait.yaml").read_text()
    keys = [line.split(":")[0] for line in text.splitlines() if line and not line.startswith((" ", "#", "-"))]
    assert keys[:3] == ["format", "frames", "units"]
    assert doc["format"] == "graphcal-plan-gait/1"
    assert set(doc["frames"]) >= {"world", "stairs"} and "m" in doc["units"]["length"]
    T_ws = np.array(doc["T_world_stairs"])
    for _, _, fh in _footholds(doc):
        p_w = T_ws[:3, :3] @ np.array(fh["p_stairs_foot"]) + T_ws[:3, 3]
        assert np.allclose(p_w, fh["p_world_foot"], atol=1e-5)
        assert fh["surface"] in ("floor", "tread 0", "tread 1", "tread 2")
        assert set(fh["swing"]["clearance_over_nosing_m"]) == {"tread 0", "tread 1", "tread 2"}
    assert sorted(doc["output_files"]) == sorted(p.name for p in plan.iterdir())


def test_report_has_its_side_and_top_figures(planned):
    _, _, plan, doc = planned
    html = (plan / "report.html").read_text()
    assert html.count('<img src="data:image/png;base64,') == 2
    assert "side.png: side view" in html and "top.png: top view" in html
    for name in ("side.png", "top.png"):
        assert (plan / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "tread 2 (the top one)" in html  # the warning box


def test_top_tread_seen_in_part_is_warned_by_name_and_kept_inside_what_was_seen(planned):
    """The landing's back edge is never seen (depth_complete false): the plan keeps its feet at least
    the far zone inside what was seen and says so, naming the tread."""
    _, _, _, doc = planned
    top = doc["treads"][-1]
    assert top["depth_complete"] is False and top["trust"] == "seen part only"
    assert any("tread 2 (the top one)" in w and "depth incomplete" in w for w in doc["warnings"])
    on_top = [fh for _, _, fh in _footholds(doc) if fh["surface"] == "tread 2"]
    assert on_top and all(fh["seen_end_distance_m"] >= CFG.far_zone_m - 1e-6 for fh in on_top)
    if doc["summary"]["outcome"] != "climbed":  # honest about where the plan stops
        assert any("does not reach the top" in w for w in doc["warnings"])


def _refused(capsys, track, out, *extra):
    capsys.readouterr()
    code = main(["plan-gait", str(track), "--out", str(out), "--quiet", *extra])
    err = capsys.readouterr().err.strip().splitlines()
    return code, err


def test_a_bad_track_dir_gives_one_line_and_exit_2(planned, tmp_path, capsys):
    _, track, _, _ = planned
    bad = tmp_path / "track_without_stairs"
    bad.mkdir()
    shutil.copy(track / "metrics.json", bad / "metrics.json")
    shutil.copy(track / "trajectory.tum", bad / "trajectory.tum")
    code, err = _refused(capsys, bad, tmp_path / "out")
    assert code == 2 and len(err) == 1 and "stairs.json: no such file" in err[0], err
    assert not (tmp_path / "out").exists()
    code, err = _refused(capsys, tmp_path / "nowhere", tmp_path / "out")
    assert code == 2 and len(err) == 1 and "no such folder" in err[0], err
    code, err = _refused(capsys, track, track / "plan")  # never into its input
    assert code == 2 and len(err) == 1 and "inside the track output" in err[0], err
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    code, err = _refused(capsys, track, foreign)
    assert code == 2 and len(err) == 1 and "holds no graphcal plan-gait output" in err[0], err
    assert (foreign / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("change, named", [
    ({"index": 1, "depth_complete": False}, "tread 1 of"),
    ({"index": 0, "n_inliers": 40}, "tread 0 of"),
])
def test_a_tread_not_seen_well_enough_is_refused_by_name(planned, tmp_path, capsys, change, named):
    _, track, _, _ = planned
    copy = tmp_path / "track"
    shutil.copytree(track, copy)
    doc = json.loads((copy / "stairs.json").read_text())
    tread = next(t for t in doc["treads"] if t["index"] == change["index"])
    tread.update({k: v for k, v in change.items() if k != "index"})
    (copy / "stairs.json").write_text(json.dumps(doc))
    code, err = _refused(capsys, copy, tmp_path / "out")
    assert code == 2 and len(err) == 1, err
    assert named in err[0] and "guessed edge" in err[0], err
    assert ("depth incomplete" in err[0]) if "depth_complete" in change else ("40 points" in err[0])
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- helpers
def _steps():
    return [Stair(1.2, 0.3, 0.13, 1.6), Stair(1.5, 0.3, 0.26, 1.6), Stair(1.8, 1.0, 0.39, 1.6)]


def test_stairs_json_round_trip_recovers_the_extents():
    model = stairs_model_from_steps(_steps())
    back = stairs_model_from_json(json.loads(json.dumps(stairs_to_json(model))))
    for a, b in zip(model.treads, back.treads):
        assert (b.s_front_m, b.s_back_m, b.t_min_m, b.t_max_m) == pytest.approx(
            (a.s_front_m, a.s_back_m, a.t_min_m, a.t_max_m), abs=1e-9)
    assert np.allclose(back.T_world_stairs, model.T_world_stairs)
    with pytest.raises(GaitError, match="could not model the stairs: no floor"):
        stairs_model_from_json({"error": "no floor"})
    with pytest.raises(GaitError, match=r"treads\[0\]: height_m"):
        stairs_model_from_json({**stairs_to_json(model), "treads": [{**stairs_to_json(model)["treads"][0],
                                                                      "height_m": "high"}]})


def test_edge_distances_and_trust_on_known_stairs():
    model = stairs_model_from_steps(_steps())  # stairs frame = world shifted by 1.2 m along x
    d_n, i_n, d_r, i_r = edge_distances(model, [1.30, 0.0, 0.13])  # on tread 0, 10 cm behind its nosing
    assert (d_n, i_n) == pytest.approx((0.10, 0)) and (d_r, i_r) == pytest.approx((0.10, 0))  # riser 0's top
    d_n, _, d_r, i_r = edge_distances(model, [1.10, 0.0, 0.0])  # on the floor, 10 cm before the first riser
    assert d_r == pytest.approx(0.10) and i_r == 0 and d_n == pytest.approx(np.hypot(0.10, 0.13))
    assert [t.status for t in tread_trust(model, min_tread_points=0)] == ["seen"] * 3  # the exact model: complete
    refused = tread_trust(model)  # ... but it has no points
    assert [t.status for t in refused] == ["refused"] * 3 and "0 points (fewer than 150)" in refused[0].reason
    top_open = stairs_model_from_json({**stairs_to_json(model), "treads": [
        {**t, "n_inliers": 500, "depth_complete": t["index"] < 2} for t in stairs_to_json(model)["treads"]]})
    assert [t.status for t in tread_trust(top_open)] == ["seen", "seen", "seen part only"]


def test_stability_margin_of_a_triangle():
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [0.0, 1.0, 0.0]])
    m = stability_margin(tri, np.array([[0.25, 0.25, 0.5], [0.5, -0.2, 0.5], [0.0, 0.0, 0.4]]))
    assert m == pytest.approx([0.25, -0.2, 0.0])
    assert float(stability_margin(tri[[2, 0, 1]], [0.25, 0.25, 0.0])) == pytest.approx(0.25)  # any order


def test_report_3d_scene_holds_the_plans_footholds_and_body_path(planned):
    import json
    import re

    _, _, plan, doc = planned
    text = (plan / "report.html").read_text()
    payload = json.loads(re.search(r'<script type="application/json">(.*?)</script>', text, re.S).group(1))
    groups = {g["name"]: np.asarray(g["data"], dtype=float).reshape(-1, 3) for g in payload["groups"]}
    assert {"stairs (perceived)", "planned body path", "planned footholds", "feet at the start"} <= set(groups)
    # the page's points (mm, about the scene's centre) are gait.yaml's footholds, in order
    want = np.array([fh["p_world_foot"] for _, _, fh in _footholds(doc)])
    got = groups["planned footholds"]
    centre = (got - 1e3 * want).mean(axis=0)
    assert len(got) == len(want) and np.max(np.abs(got - 1e3 * want - centre)) <= 1.0  # rounded to 1 mm
    assert groups["planned body path"].shape[0] == 2 * len(doc["steps"])  # one segment per step
