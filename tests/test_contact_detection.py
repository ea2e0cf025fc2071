"""Contacts from real signals (issue 42 item 2): per-foot thresholds learned from each foot's own
force signal (raw counts with per-foot offsets and gains, or N), a hysteresis and minimum stance
and swing durations; the filter tracks raw counts as it tracks N; the import keeps force_<foot>
beside contact_<foot> and takes JointState efforts into tau_<joint>."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.errors import GraphcalError

#: per-foot (offset counts, gain N/count): standing (~30 N a foot) fl reads ~92 counts, the others 240-310
COUNTS = {"fl_foot": (20.0, 30.0 / 72.0), "fr_foot": (10.0, 0.12), "rl_foot": (30.0, 30.0 / 210.0),
          "rr_foot": (5.0, 0.1)}


@pytest.fixture(scope="module")
def trot():
    """The a1 trotting 8 s at 400 Hz (force sensors, 1.5 s standing at each end)."""
    from graphcal.simulation.walking import WalkingConfig, simulate_walking

    return simulate_walking(WalkingConfig(program="trot", robot="a1", duration_s=8.0, rate_hz=400.0,
                                          still_s=1.5, cloud_rate_hz=0.0, seed=3))


def _counts(r):
    from graphcal.simulation.write import force_counts_of

    return force_counts_of(r.foot_force, r.feet, COUNTS)


def _transitions(mask):
    return int(np.count_nonzero(np.diff(mask.astype(int), axis=0)))


def test_learned_thresholds_on_counts_with_per_foot_offsets_and_gains(trot):
    from graphcal.locomotion.contact_detection import detect_contacts

    r = trot
    counts = _counts(r)
    standing = np.median(counts[: int(1.0 * 400)], axis=0)
    assert standing[0] == pytest.approx(92, abs=4) and np.all((standing[1:] > 235) & (standing[1:] < 315))
    det = detect_contacts(counts, r.times, r.feet)
    in_n = detect_contacts(r.foot_force, r.times, r.feet)
    for i, (f, fc) in enumerate(zip(r.feet, det.feet)):
        t = fc.thresholds
        off, gain = COUNTS[f]
        assert t.source == "learned" and t.off < t.on
        assert t.low_mode == pytest.approx(off, abs=3)  # the swing mode is the sensor's offset
        assert t.on == pytest.approx(off + in_n.feet[i].thresholds.on / gain, rel=0.05)  # equivariant
        assert fc.duty_factor == pytest.approx(r.contact[:, i].mean(), abs=0.02)
    assert np.mean(det.mask == r.contact) > 0.98
    assert np.count_nonzero(det.mask & ~r.contact) == 0  # never a swinging foot taken for planted
    assert np.count_nonzero(det.mask != in_n.mask) <= 2 * _transitions(r.contact) // 10 + 4
    # one common threshold on counts (today's 20 N hysteresis applied to them): the feet "loaded" in swing
    fixed = detect_contacts(counts, r.times, r.feet, thresholds="fixed", fixed=(20.0, 10.0))
    assert np.count_nonzero(fixed.mask & ~r.contact) > 300


def test_no_two_modes_is_an_error_naming_the_foot_or_the_fallback():
    from graphcal.locomotion.contact_detection import ContactSignalError, detect_contacts, learn_thresholds

    rng = np.random.default_rng(0)
    t = np.arange(2000) / 400.0
    for signal in (np.full(2000, 92.0), rng.normal(92.0, 3.0, 2000), np.round(rng.normal(92.0, 3.0, 2000))):
        with pytest.raises(ContactSignalError, match="foot rl_foot: expected .* (two separated modes|a swing)"):
            learn_thresholds(signal, "rl_foot")
    x = np.column_stack([np.full(2000, 92.0), np.where((t % 0.5) < 0.3, 250.0, 20.0)])
    with pytest.raises(ContactSignalError, match="fl_foot"):
        detect_contacts(x, t, ("fl_foot", "fr_foot"))
    det = detect_contacts(x, t, ("fl_foot", "fr_foot"), fallback=(20.0, 10.0))
    assert [f.thresholds.source for f in det.feet] == ["fallback", "learned"] and det.mask[:, 0].all()
    with pytest.raises(GraphcalError, match="contact_thresholds"):
        from graphcal.locomotion.estimator import TrackerConfig

        TrackerConfig(contact_thresholds="otsu")


def test_spurious_short_stances_and_swings_removed():
    """A 2 Hz gait at 400 Hz (stance 0.3 s) with 10 spurious stances of 5-35 ms in its swings and 3
    dips of 10-20 ms in its stances: the mask is the gait's, the removed runs counted."""
    from graphcal.locomotion.contact_detection import detect_contacts

    rng = np.random.default_rng(1)
    t = np.arange(4000) / 400.0
    truth = (t % 0.5) < 0.3
    x = np.where(truth, 260.0, 25.0) + rng.normal(0.0, 4.0, len(t))
    swing_starts = np.flatnonzero(np.diff(truth.astype(int)) == -1)[:10] + 1
    for k, s in enumerate(swing_starts):
        n = 2 + k  # 2..11 samples: 5..27.5 ms
        x[s + 20 : s + 20 + n] = 240.0
    stance_starts = np.flatnonzero(np.diff(truth.astype(int)) == 1)[2:5] + 1
    for k, s in enumerate(stance_starts):
        x[s + 40 : s + 44 + 2 * k] = 20.0
    det = detect_contacts(x[:, None], t, ("fl_foot",))
    fc = det.feet[0]
    assert fc.n_short_stances == 10 and fc.n_short_swings == 3
    assert np.array_equal(det.mask[:, 0], truth)
    assert fc.n_stances == int(np.count_nonzero(np.diff(truth.astype(int)) == 1)) + 1


def _track(folder: Path):
    from graphcal.io.dataset import read_dataset
    from graphcal.locomotion.consistency import consistency_verdict
    from graphcal.locomotion.estimator import TrackerConfig, run_filter
    from graphcal.locomotion.track_inputs import inputs_from_dataset

    res = run_filter(inputs_from_dataset(read_dataset(folder)), TrackerConfig(icp=False))
    verdict = consistency_verdict({"stance": (res.stance_times, res.stance_nis, res.stance_dofs)})
    return res, verdict


def test_trot_in_raw_counts_tracks_like_in_newtons(trot, tmp_path):
    from graphcal.simulation.write import write_walking

    r = trot
    write_walking(r, tmp_path / "n")
    write_walking(r, tmp_path / "counts", force_counts=COUNTS)
    res_n, v_n = _track(tmp_path / "n")
    res_c, v_c = _track(tmp_path / "counts")
    per_transition = np.count_nonzero(res_c.stance_mask != res_n.stance_mask) / max(1, _transitions(res_n.stance_mask))
    assert per_transition <= 3.0
    assert v_c["verdict"] != "inconsistent" and v_n["verdict"] != "inconsistent"
    drift = np.linalg.norm(res_c.T_world_body[-1, :3, 3] - r.T_world_body[-1, :3, 3]) / r.distance_m
    assert drift <= 0.01
    c = res_c.contacts
    assert c["signal"] == "force_<foot>" and c["thresholds"] == "learned" and c["min_stance_s"] == 0.05
    assert set(c["feet"]) == set(r.feet) and all(f["source"] == "learned" for f in c["feet"].values())
    assert c["feet"]["fl_foot"]["low_mode"] == pytest.approx(20.0, abs=3)
    assert c["feet"]["fl_foot"]["duty_factor"] == pytest.approx(r.contact[:, 0].mean(), abs=0.02)


def test_csv_import_keeps_force_columns_and_learns_contacts(trot, tmp_path):
    """A Unitree-style CSV of the trot with raw counts (per-foot offsets and gains) and a map that
    gives no threshold: force_<foot> in counts beside contact_<foot>, the contacts learned per foot,
    the standing windows at both ends kept as stations."""
    from graphcal.commands import import_log
    from graphcal.io.dataset import read_dataset
    from graphcal.simulation.ros_log import write_walk_csv
    from graphcal.simulation.write import write_walking

    write_walking(trot, tmp_path / "sim", force_counts=COUNTS)
    cmap = yaml.safe_load(write_walk_csv(tmp_path / "sim", tmp_path / "log.csv", raw_scale=1.0, raw_offset=0.0))
    cmap["feet"] = {f: {"column": spec["column"]} for f, spec in cmap["feet"].items()}  # counts, no threshold
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(cmap))
    result = import_log.run(tmp_path / "log.csv", tmp_path / "ds", map_path=tmp_path / "map.yaml", timeseries=True,
                            progress=False)
    assert result.n_stations == 2
    ts = read_dataset(tmp_path / "ds").timeseries
    counts = _counts(trot)
    for i, f in enumerate(trot.feet):
        assert np.allclose(np.asarray(ts[f"force_{f}"], dtype=float), counts[:, i])
        contact = np.asarray(ts[f"contact_{f}"], dtype=float) > 0.5
        assert np.mean(contact == trot.contact[:, i]) > 0.98 and not np.any(contact & ~trot.contact[:, i])
    report = yaml.safe_load((tmp_path / "ds" / "import_report.yaml").read_text())
    fl = report["contacts"]["feet"]["fl_foot"]
    assert fl["source"] == "learned" and fl["low_mode"] == pytest.approx(20.0, abs=3) and fl["off"] < fl["on"]


JOINTS = [f"{leg}_{j}_joint" for leg in ("lf", "lm", "lr", "rf", "rm", "rr") for j in ("coxa", "femur", "tibia")]


def _effort_bag(path: Path, n: int = 60) -> Path:
    """A ROS 1 bag of JointState messages with positions and efforts (the efforts in reversed
    name order from message 10 on: reordered by name)."""
    from rosbags.rosbag1 import Writer

    from graphcal.logs.reader import default_typestore

    ts = default_typestore("ros1")
    T = ts.types
    typ = "sensor_msgs/msg/JointState"
    with Writer(path) as w:
        c = w.add_connection("/joint_states", typ, typestore=ts)
        for i in range(n):
            t = 100.0 + 0.01 * i
            stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
            names, effort = list(JOINTS), 0.1 * np.arange(len(JOINTS)) + i
            if i >= 10:
                names, effort = names[::-1], np.ascontiguousarray(effort[::-1])
            msg = T[typ](header=T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=""), name=names,
                         position=np.zeros(len(JOINTS)), velocity=np.zeros(0), effort=effort)
            w.write(c, int(1e9 * t), ts.serialize_ros1(msg, typ))
    return path


def test_bag_joint_state_efforts_become_tau_columns(tmp_path):
    from graphcal.commands import import_log
    from graphcal.io.dataset import read_dataset
    from graphcal.models.builtin import builtin_urdf

    (tmp_path / "robot.urdf").write_text(builtin_urdf("octopus"))
    log = _effort_bag(tmp_path / "log.bag")
    import_log.run(log, tmp_path / "ds", urdf=tmp_path / "robot.urdf", timeseries=True, progress=False)
    ts = read_dataset(tmp_path / "ds").timeseries
    for k, j in enumerate(JOINTS):
        assert np.allclose(np.asarray(ts[f"tau_{j}"], dtype=float), 0.1 * k + np.arange(60))
