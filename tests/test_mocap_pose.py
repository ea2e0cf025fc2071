"""The 6-D motion-capture pose kind: factor (error, analytic Jacobians against central differences),
contract (mocap_poses.csv read, validated, written), simulation and identification from it."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from graphcal.factors.mocap_pose import mocap_pose_error
from graphcal.geometry import pose_from_xyz_rpy, so3_log_batch, so3_right_jacobian_inverse_batch
from graphcal.models.legs import leg_model
from graphcal.models.robot import load_robot

DEG = np.pi / 180.0
FOOT = "fl_foot"


def _setup(seed=3, n=4):
    robot = load_robot(model="a1", base_frame="body", feet=(FOOT,))
    leg = robot.leg(FOOT)
    model = leg_model(robot, FOOT, origins="first")
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.5, 0.5, size=(n, leg.n_joints))
    theta = rng.normal(0, 0.01, model.dim)
    T = pose_from_xyz_rpy([0.3, -0.1, 0.2], [0.1, -0.2, 0.4])
    Tm = np.array([pose_from_xyz_rpy(rng.normal(0, 0.3, 3), rng.normal(0, 0.5, 3)) for _ in range(n)])
    return leg, model, q, theta, T, Tm


def test_so3_helpers():
    x = np.array([[0.3, -0.2, 0.5], [1e-9, 0, 0]])
    R = np.array([gtsam.Rot3.Expmap(v).matrix() for v in x])
    assert np.allclose(so3_log_batch(R), x, atol=1e-12)
    # Jr^-1 inverts the right Jacobian: Log(Exp(x) Exp(d)) ~ x + Jr^-1 d
    d = 1e-6 * np.array([0.2, 0.7, -0.4])
    y = gtsam.Rot3.Logmap(gtsam.Rot3.Expmap(x[0]) * gtsam.Rot3.Expmap(d))
    assert np.allclose((y - x[0]) / 1e-6, so3_right_jacobian_inverse_batch(x[:1])[0] @ d / 1e-6, atol=1e-5)


def test_pose_error_jacobians_match_central_differences():
    leg, model, q, theta, T, Tm = _setup()
    e, (HV, HL) = mocap_pose_error(T, theta, q, Tm, leg, model, True)
    h = 1e-6
    num_V = np.zeros_like(HV)
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = h
        ep = mocap_pose_error(gtsam.Pose3(T).retract(dx).matrix(), theta, q, Tm, leg, model, False)[0]
        em = mocap_pose_error(gtsam.Pose3(T).retract(-dx).matrix(), theta, q, Tm, leg, model, False)[0]
        num_V[:, :, i] = (ep - em) / (2 * h)
    num_L = np.zeros_like(HL)
    for i in range(model.dim):
        dt = np.zeros(model.dim)
        dt[i] = h
        ep = mocap_pose_error(T, theta + dt, q, Tm, leg, model, False)[0]
        em = mocap_pose_error(T, theta - dt, q, Tm, leg, model, False)[0]
        num_L[:, :, i] = (ep - em) / (2 * h)
    assert np.max(np.abs(HV - num_V)) < 1e-6, np.max(np.abs(HV - num_V))
    assert np.max(np.abs(HL - num_L)) < 1e-6, np.max(np.abs(HL - num_L))
    # a wrong sign in any block would miss: the Jacobians are not small
    assert np.max(np.abs(HV)) > 0.1 and np.max(np.abs(HL)) > 0.1


# ----------------------------------------------------------------------------- contract + identification
from graphcal.errors import DatasetError  # noqa: E402
from graphcal.legs.identify import IdentifyOptions, identify_legs_dataset  # noqa: E402
from graphcal.models.legs import theta_from_perturbation  # noqa: E402
from graphcal.models.perturb import LegPerturbation  # noqa: E402
from graphcal.simulation.mocap import simulate_mocap, write_mocap_simulation  # noqa: E402

POSE_SIGMA = [0.2 * DEG] * 3 + [0.001] * 3
PERT = LegPerturbation({"fl_thigh_joint": 1.5 * DEG, "fl_calf_joint": -2.0 * DEG},
                       {"fl_thigh_joint": (0.0, 0.004, 0.0), "fl_calf_joint": (0.0, 0.0, -0.010),
                        "fl_foot_joint": (0.0, 0.0, 0.015)})


@pytest.fixture(scope="module")
def pose_dataset(tmp_path_factory):
    sim = simulate_mocap("a1", feet=(FOOT,), n_samples=120, perturbation=PERT, body_markers=False, foot_markers=False,
                         pose_sigma=POSE_SIGMA, seed=7)
    return write_mocap_simulation(sim, tmp_path_factory.mktemp("poses") / "ds"), sim


def test_pose_kind_identifies_the_simulated_leg_within_3_sigma(pose_dataset):
    path, sim = pose_dataset
    assert (path / "mocap_poses.csv").is_file() and not (path / "mocap.csv").exists()
    res = identify_legs_dataset(path, options=IdentifyOptions(noise_source="dataset"))
    truth = theta_from_perturbation(res.models[FOOT], PERT)
    checked = 0
    for p, t in zip(res.legs[FOOT], truth):
        if p.free:
            assert abs(p.value - t) < 3 * p.sigma, (p.name, p.value, t, p.sigma)
            checked += 1
    assert checked >= 5
    # the pose of the measurement frame: within 3 sigma too, and far better than the 1 mm per pose
    xi = np.asarray(gtsam.Pose3(sim.T_body_mocap_true).localCoordinates(gtsam.Pose3(res.T_body_mocap)))
    s = np.sqrt(np.diag(res.T_body_mocap_covariance))
    assert np.all(np.abs(xi) < 3 * s) and s[3:].max() < 0.001, (xi, s)
    # 6 rows per posture, the verdict on clean data
    assert res.dof == 6 * 120 - sum(p.free for p in res.identifiability.parameters)
    assert res.adequacy.verdict == "fits" and not res.adequacy.flagged


def test_pose_rows_are_validated(pose_dataset, tmp_path):
    import shutil

    path, _ = pose_dataset
    text = (path / "mocap_poses.csv").read_text().splitlines()
    header = text[0].split(",")
    for col, value, expected in (("qw", "0.5", "a unit quaternion"), ("frame", "fr_foot", "a frame of robot.feet"),
                                 ("sigma_x", "0", "a standard deviation > 0"), ("x", "300", "metres")):
        bad = tmp_path / f"bad_{col}"
        shutil.copytree(path, bad)
        row = text[3].split(",")
        row[header.index(col)] = value
        (bad / "mocap_poses.csv").write_text("\n".join(text[:3] + [",".join(row)] + text[4:]) + "\n")
        with pytest.raises(DatasetError) as e:
            identify_legs_dataset(bad)
        msg = str(e.value)
        assert "mocap_poses.csv" in msg and "row 3" in msg and expected in msg, msg


def test_poses_beside_markers_in_the_virtual_base():
    """mocap_poses.csv beside mocap.csv with Yuan's body markers: the poses are re-expressed in the
    virtual base, both kinds enter one fit, the leg is found within 3 sigma and the fit is judged."""
    pert = LegPerturbation({"fl_thigh_joint": 1.5 * DEG, "fl_calf_joint": -2.0 * DEG},
                           {"fl_calf_joint": (0.0, 0.0, -0.010), "fl_foot_joint": (0.0, 0.0, 0.015)})
    sim = simulate_mocap("a1", feet=(FOOT,), n_samples=100, perturbation=pert, marker_noise_m=0.0005, noise="gaussian",
                         body_marker_noise_m=0.0, pose_sigma=POSE_SIGMA, seed=5)
    res = identify_legs_dataset(sim.dataset, options=IdentifyOptions(noise_source="dataset"))
    assert res.frame == "vbase" and [r.marker for r in res.residuals] == [FOOT, f"pose:{FOOT}"]
    assert res.dof == (3 + 6) * 100 - sum(p.free for p in res.identifiability.parameters)
    truth = theta_from_perturbation(res.models[FOOT], pert)
    free = [(p, t) for p, t in zip(res.legs[FOOT], truth) if p.free]
    assert len(free) == 5 and all(abs(p.value - t) < 3 * p.sigma for p, t in free), free
    assert res.adequacy.verdict == "fits" and res.adequacy.flagged == ()


def test_full_covariance_columns_read_like_the_sigmas(pose_dataset, tmp_path):
    """cov_00 ... cov_55 with diag(sigma^2) give the same identification as the sigma columns; an
    asymmetric or indefinite covariance is refused with the row named."""
    import csv
    import shutil

    path, _ = pose_dataset
    rows = list(csv.DictReader(open(path / "mocap_poses.csv")))
    names = ("sigma_rx", "sigma_ry", "sigma_rz", "sigma_x", "sigma_y", "sigma_z")
    base = ["time", "frame", "x", "y", "z", "qw", "qx", "qy", "qz"]
    cov_cols = [f"cov_{i}{j}" for i in range(6) for j in range(6)]

    def write(folder, edit=None):
        shutil.copytree(path, folder)
        with open(folder / "mocap_poses.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(base + cov_cols)
            for k, r in enumerate(rows):
                C = np.diag([float(r[n]) ** 2 for n in names])
                if edit is not None and k == 2:
                    edit(C)
                w.writerow([r[c] for c in base] + [repr(float(x)) for x in C.reshape(-1)])
        return folder

    a = identify_legs_dataset(path)
    b = identify_legs_dataset(write(tmp_path / "cov"))
    assert np.allclose(a.theta[FOOT], b.theta[FOOT], rtol=0, atol=1e-12)
    assert a.adequacy.statistic == pytest.approx(b.adequacy.statistic, rel=1e-9)

    def asym(C):
        C[0, 1] = 1e-6

    def indefinite(C):
        C[3, 3] = -1e-6

    for edit, words in ((asym, "a symmetric covariance"), (indefinite, "a positive definite covariance")):
        with pytest.raises(DatasetError) as e:
            identify_legs_dataset(write(tmp_path / edit.__name__, edit))
        assert "mocap_poses.csv: row 3 (line 4), column cov_00..cov_55" in str(e.value) and words in str(e.value)
