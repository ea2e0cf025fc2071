"""Issue 30's end-to-end case: a simulated quadruped trot exported as a Unitree-style CSV log with raw
foot-force counts -> ``graphcal import`` -> ``graphcal track``: the stance comes from the raw counts
(offset and scale of the column map), and the drift stays within 1 % of the distance."""

from __future__ import annotations

import json
import shutil

import pytest

from graphcal.cli import main
from graphcal.simulation.ros_log import write_walk_csv


@pytest.mark.slow
def test_a_trot_csv_log_imports_and_tracks_within_one_percent(tmp_path):
    sim = tmp_path / "trot"
    assert main(["simulate", "--robot", "a1", "--program", "trot", "--distance", "6", "--out", str(sim), "--quiet"]) == 0
    log = tmp_path / "log.csv"
    cmap = tmp_path / "map.yaml"
    cmap.write_text(write_walk_csv(sim, log))
    ds = tmp_path / "imported"
    assert main(["import", str(log), "--map", str(cmap), "--timeseries", "--out", str(ds), "--quiet"]) == 0
    header = (ds / "timeseries.csv").read_text().splitlines()[0].split(",")
    assert [c for c in header if c.startswith("contact_")] == [f"contact_{f}" for f in
                                                                ("fl_foot", "fr_foot", "rl_foot", "rr_foot")]
    # the raw counts are kept beside the contacts decided from them; no torques: stance comes from the counts
    assert [c for c in header if c.startswith("force_")] and not [c for c in header if c.startswith("tau_")]
    shutil.copy(sim / "truth.yaml", ds / "truth.yaml")  # the simulator's hidden truth, for the metrics
    shutil.copy(sim / "truth_trajectory.csv", ds / "truth_trajectory.csv")
    assert main(["track", str(ds), "--out", str(tmp_path / "track"), "--quiet"]) == 0
    metrics = json.loads((tmp_path / "track" / "metrics.json").read_text())
    assert metrics["truth"]  # compared with the truth, not estimated from the filter alone
    assert 0.0 < metrics["drift_percent"] <= 1.0
    assert metrics["consistency"]["verdict"] == "consistent"
