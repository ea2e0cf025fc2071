"""The walking simulator (graphcal.simulation.walking): tripod gait, planted feet, swing clearance,
IMU, torques and clouds consistent with the truth; support detection from the torques; the
``graphcal simulate --program tripod-walk|tripod-stairs`` folder in the contract.

Every check recomputes what it checks by an independent route (forward kinematics of the true
joint angles, finite differences of the truth, terrain ray casting)."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import GraphcalError
from graphcal.models.kinematics import foot_positions
from graphcal.simulation.terrain import stair_profile
from graphcal.simulation.walking import GRAVITY_M_S2, WalkingConfig, simulate_walking

QINGZHUI_GROUP_A = ("mf_foot", "rb_foot", "lb_foot")  # Zhao Fig. 4
QINGZHUI_GROUP_B = ("mb_foot", "rf_foot", "lf_foot")


@pytest.fixture(scope="module")
def level():
    return simulate_walking(WalkingConfig(program="tripod-walk", distance_m=3.0, cloud_rate_hz=4.0, seed=1))


@pytest.fixture(scope="module")
def stairs():
    return simulate_walking(WalkingConfig(program="tripod-stairs", cloud_rate_hz=1.0, seed=2))


def _feet_world(walk):
    """Foot positions in the world from the TRUE joint angles and the true body poses (FK)."""
    out = []
    for f in walk.feet:
        leg = walk.robot.leg(f)
        q = np.column_stack([walk.q_true[j] for j in leg.joint_names])
        p_body = foot_positions(leg, q)
        out.append(np.einsum("nij,nj->ni", walk.T_world_body[:, :3, :3], p_body) + walk.T_world_body[:, :3, 3])
    return np.array(out)


@pytest.mark.parametrize("name", ["level", "stairs"])
def test_feet_planted_in_stance_and_above_ground_in_swing(name, request):
    walk = request.getfixturevalue(name)
    pw = _feet_world(walk)
    ground = (lambda x: stair_profile(walk.terrain.stairs, x)) if walk.config.stairs else (lambda x: 0.0 * x)
    for i, f in enumerate(walk.feet):
        c = walk.contact[:, i]
        both = c[1:] & c[:-1]
        # planted: the FK foot does not move during a stance (sub-micrometre; IK residual < 1e-9 m)
        assert np.abs(np.diff(pw[i], axis=0)[both]).max() < 1e-8, f
        # on the ground while planted, above it while swinging
        assert np.abs(pw[i, c, 2] - ground(pw[i, c, 0])).max() < 1e-8, f
        assert (pw[i, ~c, 2] - ground(pw[i, ~c, 0])).min() > -1e-9, f
        # a swing really lifts: the highest point of every swing is >= 5 cm above the ground under it
        starts = np.flatnonzero(np.diff(c.astype(int)) == -1) + 1
        ends = np.flatnonzero(np.diff(c.astype(int)) == 1) + 1
        for a, b in zip(starts, ends[ends > starts[0]] if len(starts) else []):
            gap = pw[i, a:b, 2] - ground(pw[i, a:b, 0])
            assert gap.max() > 0.05, (f, a)


def test_alternating_tripod_gait(level):
    """Zhao Fig. 4: the two tripods alternate, with a short six-foot support at each switch;
    never fewer than three feet down."""
    assert set(level.groups[0]) == set(QINGZHUI_GROUP_A) and set(level.groups[1]) == set(QINGZHUI_GROUP_B)
    col = {f: i for i, f in enumerate(level.feet)}
    A = level.contact[:, [col[f] for f in QINGZHUI_GROUP_A]]
    B = level.contact[:, [col[f] for f in QINGZHUI_GROUP_B]]
    assert (A.all(axis=1) == A.any(axis=1)).all() and (B.all(axis=1) == B.any(axis=1)).all()  # groups move together
    assert (A[:, 0] | B[:, 0]).all()  # always one tripod down
    swinging = ~A[:, 0] | ~B[:, 0]
    duty = 1.0 - np.mean(~A[swinging, 0])  # over the walking part
    assert 0.5 < duty < 0.6  # ~ half a cycle each (duty factor 0.55 of the cycle; both down 10 % of it)
    n_switch_A = np.count_nonzero(np.diff(A[:, 0].astype(int)) == -1)
    n_cycles = (level.times[-1] - 2 * level.config.still_s) / level.config.cycle_s
    assert abs(n_switch_A - n_cycles) <= 1.5


@pytest.mark.parametrize("name", ["level", "stairs"])
def test_imu_is_the_truth_plus_its_noise(name, request):
    """Specific force and rate recomputed from the true poses by finite differences match the
    simulated IMU (minus its true bias) to the IMU's white noise (within 10 %) with ~zero mean."""
    walk = request.getfixturevalue(name)
    c = walk.config
    dt = 1.0 / c.rate_hz
    T = walk.T_world_body
    p = T[:, :3, 3]
    a = np.gradient(np.gradient(p, dt, axis=0), dt, axis=0)
    f_true = np.einsum("nji,nj->ni", T[:, :3, :3], a - np.array([0.0, 0.0, -GRAVITY_M_S2]))
    dR = np.einsum("nji,njk->nik", T[:-2, :3, :3], T[2:, :3, :3])  # R_{k-1}^T R_{k+1}
    w_true = np.c_[dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]] / (4 * dt)
    inner = slice(5, -5)
    ea = (walk.imu_accel - walk.accel_bias - f_true)[inner]
    eg = (walk.imu_gyro - walk.gyro_bias)[1:-1][4:-4] - w_true[4:-4]
    sa = c.accel_noise_density * np.sqrt(c.rate_hz)
    sg = c.gyro_noise_density * np.sqrt(c.rate_hz)
    assert np.std(ea, axis=0) == pytest.approx([sa] * 3, rel=0.1)
    assert np.std(eg, axis=0) == pytest.approx([sg] * 3, rel=0.1)
    assert np.abs(ea.mean(axis=0)).max() < 5 * sa / np.sqrt(len(ea)) + 1e-4
    assert np.abs(eg.mean(axis=0)).max() < 5 * sg / np.sqrt(len(eg)) + 1e-5


def test_torques_carry_the_body_quasi_statically(level):
    """Tip forces recovered from the measured torques (Zhao Eq. 5) carry m (g + a_z) vertically:
    the error, normalised by the torque noise propagated through each leg's J^-T, is unit noise."""
    from graphcal.locomotion.support import tip_forces
    from graphcal.models.kinematics import leg_jacobian

    total = np.zeros((len(level.times), 3))
    var = np.zeros(len(level.times))
    s_tau = level.config.torque_sigma_nm
    for f in level.feet:
        leg = level.robot.leg(f)
        q = np.column_stack([level.q_measured[j] for j in leg.joint_names])
        tau = np.column_stack([level.tau_measured[j] for j in leg.joint_names])
        total += np.einsum("nij,nj->ni", level.T_world_body[:, :3, :3], tip_forces(leg, q, tau))
        Jinv_T = np.linalg.inv(np.swapaxes(leg_jacobian(leg, q), 1, 2))
        up = level.T_world_body[:, 2, :3]  # world z in the body frame
        g = np.einsum("ni,nij->nj", up, Jinv_T)
        var += s_tau**2 * np.einsum("nj,nj->n", g, g)
    a_z = np.gradient(np.gradient(level.T_world_body[:, 2, 3], 1e-3), 1e-3)
    expected = -level.config.body_mass_kg * (GRAVITY_M_S2 + a_z)  # the feet push down
    z = ((total[:, 2] - expected) / np.sqrt(var))[10:-10]
    assert abs(z.mean()) < 0.05
    assert np.sqrt(np.mean(z**2)) == pytest.approx(1.0, abs=0.1)
    assert np.median(np.abs(expected)) == pytest.approx(level.config.body_mass_kg * GRAVITY_M_S2, rel=0.01)


def test_support_detection_from_torques_matches_the_contacts(level, stairs):
    """Zhao: the tripod with the larger vertical force sum is in stance. The detected tripod's
    feet are all planted at every sample, and during single support it is the right one."""
    from graphcal.locomotion.support import support_from_torques

    for walk in (level, stairs):
        sup = support_from_torques(walk.robot, walk.q_measured, walk.tau_measured, walk.groups)
        cols = [walk.feet.index(f) for f in sup.feet]
        truth = walk.contact[:, cols]
        mask = sup.stance_mask()
        assert (truth | ~mask).all()  # every foot believed in stance is planted
        single_a = truth[:, :3].all(axis=1) & ~truth[:, 3:].any(axis=1)
        single_b = truth[:, 3:].all(axis=1) & ~truth[:, :3].any(axis=1)
        assert (sup.group[single_a] == 0).all() and (sup.group[single_b] == 1).all()
        # no flicker: one switch per support change
        n_truth = (np.count_nonzero(np.diff(single_a.astype(int)) == 1)
                   + np.count_nonzero(np.diff(single_b.astype(int)) == 1))
        assert np.count_nonzero(np.diff(sup.group)) <= n_truth + 1


def test_stairs_footholds_clear_the_edges_and_lie_on_the_treads(stairs):
    """Footholds on the stairs: at least the edge margin from every edge; their heights equal the
    terrain's (independent vertical ray cast into the meshes)."""
    from graphcal.simulation.terrain import terrain_height

    treads = stairs.terrain.stairs
    edges = sorted({s.x_start_m for s in treads} | {s.x_start_m + s.depth_m for s in treads})
    holds = []
    for i in range(len(stairs.feet)):
        c = stairs.contact[:, i]
        starts = np.flatnonzero(np.diff(c.astype(int)) == 1) + 1
        holds.append(stairs.p_world_foot[i, starts])
    holds = np.concatenate(holds)
    d_edge = np.min(np.abs(holds[:, :1] - np.array(edges)[None, :]), axis=1)
    assert d_edge.min() >= stairs.config.edge_margin_m - 1e-9
    z_ray = terrain_height(stairs.terrain, holds[:, :2])
    assert np.abs(z_ray - holds[:, 2]).max() < 1e-5
    assert holds[:, 2].max() == pytest.approx(0.39)  # the landing, 3 x 130 mm
    # the body climbs and descends: pitch nose-up then nose-down, like Zhao's Fig. 9b
    pitch = -np.arcsin(stairs.T_world_body[:, 2, 0])
    assert np.degrees(pitch.min()) < -10 and np.degrees(pitch.max()) > 10


@pytest.mark.parametrize("name", ["level", "stairs"])
def test_clouds_lie_on_the_terrain(name, request):
    """Cloud points taken to the world with the true pose and the CAD extrinsic lie on the terrain
    meshes (Open3D distance to the surface) within the Kinect noise along the optical axis."""
    import open3d as o3d

    from graphcal.geometry import transform_points
    from graphcal.simulation.terrain import build_scene

    walk = request.getfixturevalue(name)
    scene, _ = build_scene(walk.terrain.meshes)
    assert len(walk.cloud_indices) >= 3
    for k, pts in list(zip(walk.cloud_indices, walk.clouds))[1::2]:
        assert len(pts) > 300
        pw = transform_points(walk.T_world_body[k] @ walk.T_body_sensor, pts)
        dist = scene.compute_distance(o3d.core.Tensor(pw.astype(np.float32))).numpy()
        ratio = dist / (1.425e-3 * pts[:, 2] ** 2)  # <= |noise along the ray| / sigma_z
        assert np.sqrt(np.mean(ratio**2)) < 1.0
        assert 0.2 < np.sqrt(np.mean(ratio**2))  # the noise is there
        # a wrong pose (1 cm up) is detected
        shifted = scene.compute_distance(o3d.core.Tensor((pw + [0, 0, 0.01]).astype(np.float32))).numpy()
        assert np.median(shifted) > 3 * np.median(dist)


def test_simulate_command_writes_a_contract_dataset(tmp_path):
    from graphcal.cli import main
    from graphcal.io.dataset import read_dataset, validate_dataset

    out = tmp_path / "walk"
    assert main(["simulate", "--robot", "qingzhui", "--program", "tripod-walk", "--distance", "1.0",
                 "--cloud-rate", "2", "--out", str(out), "--quiet"]) == 0
    ds = read_dataset(out)
    t = ds.timeseries
    assert ds.robot.model == "qingzhui" and ds.ground["type"] == "level"
    for c in ("time", "imu_ax", "imu_gz", "q_mf_knee_joint", "tau_lb_hip_joint", "contact_rb_foot", "cloud_depth"):
        assert t.has(c), c
    assert np.diff(t["time"]).max() == pytest.approx(1e-3)
    clouds = [c for c in t["cloud_depth"].tolist() if c]
    assert len(clouds) >= 8 and all((out / c).is_file() for c in clouds)
    assert validate_dataset(out).n_clouds == len(clouds)
    assert (out / "truth.yaml").is_file() and (out / "truth_trajectory.csv").is_file()


@pytest.mark.parametrize("words,message", [
    (["--program", "tripod-walk", "--robot", "octopus"], "qingzhui"),
    (["--program", "tripod-walk", "--robot", "qingzhui", "--effect", "ground_tilt"], "--effect"),
    (["--program", "tripod-walk", "--robot", "qingzhui", "--distance", "0.1"], "shorter than the speed ramps"),
    (["--program", "tripod-walk", "--robot", "qingzhui", "--duration", "1"],
     "duration_s 1 s is too short for a walk: it needs at least 4.9 s"),
    (["--program", "chai2015", "--distance", "3"], "walking programs"),
])
def test_bad_walking_requests_are_named(tmp_path, capsys, words, message):
    from graphcal.cli import main

    assert main(["simulate", *words, "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert message in capsys.readouterr().err


def test_walking_config_checks():
    with pytest.raises(GraphcalError, match="duty_factor"):
        WalkingConfig(duty_factor=0.5).resolved()
    with pytest.raises(GraphcalError, match="unknown walking program"):
        WalkingConfig(program="tripod-run").resolved()
    with pytest.raises(GraphcalError, match="last stair edge"):
        WalkingConfig(program="tripod-stairs", distance_m=3.0).resolved()
