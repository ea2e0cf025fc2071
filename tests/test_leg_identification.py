"""Leg identification from motion capture: Yuan's virtual base, the automatic identifiable set,
recovery of injected errors within 3 sigma, and ``graphcal identify-legs`` (files, bad input)."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml

from graphcal.errors import DatasetError, GraphcalError
from graphcal.geometry import pose_from_xyz_rpy, rot_z
from graphcal.legs.identifiability import identifiability
from graphcal.legs.identify import IdentifyOptions, identify_legs, identify_legs_dataset
from graphcal.legs.mocap_data import mocap_data_from_dataset
from graphcal.legs.virtual_base import (
    point_covariance_in_vbase,
    vbase_points,
    virtual_base,
    virtual_base_covariance,
)
from graphcal.models.legs import point_kinematics, theta_from_perturbation
from graphcal.models.perturb import LegPerturbation
from graphcal.models.robot import load_robot
from graphcal.simulation.mocap import a1_body_marker_layout, simulate_mocap, write_mocap_simulation

DEG = np.pi / 180.0
FOOT = "fl_foot"


def _log_right(T_est, T_true) -> np.ndarray:
    import gtsam

    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(T_est).between(gtsam.Pose3(T_true))))


# ----------------------------------------------------------------------------- virtual base
def test_virtual_base_origin_is_the_mean_and_axes_follow_the_body():
    layout = a1_body_marker_layout(height_m=0.06)  # LF, LR, RR, RF
    T_mocap_body = pose_from_xyz_rpy([2.0, -1.0, 0.5], [0.2, -0.1, 1.0])
    P = layout @ T_mocap_body[:3, :3].T + T_mocap_body[:3, 3]
    T = virtual_base(P)
    # Eq. 4 as printed (the sum) would put the origin at 4x the centroid, metres away
    assert np.allclose(T[:3, 3], P.mean(axis=0), atol=1e-15)
    assert np.linalg.norm(P.sum(axis=0) - T[:3, 3]) > 1.0
    # rectangle parallel to the body's x-y plane: the virtual base is the body frame raised by 6 cm
    assert np.allclose(T, T_mocap_body @ pose_from_xyz_rpy([0, 0, 0.06], [0, 0, 0]), atol=1e-12)
    # Yuan's Eq. 7 edges are anti-parallel on a rectangle: no normal from them
    assert np.linalg.norm(np.cross(P[0] - P[1], P[2] - P[3])) < 1e-12


def test_virtual_base_is_exactly_orthonormal_for_irregular_markers():
    rng = np.random.default_rng(3)
    layout = a1_body_marker_layout() + rng.normal(scale=0.01, size=(4, 3))  # not planar, not a rectangle
    layout[:, 2] += np.array([0.0, 0.01, -0.01, 0.02])
    Ts = virtual_base(np.stack([layout @ rot_z(a).T for a in np.linspace(-3, 3, 7)]))
    for T in Ts:
        R = T[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-14
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    # z is the plane normal pointing up (markers counter-clockwise seen from above), x forward
    T0 = virtual_base(layout)
    assert T0[2, 2] > 0.99 and T0[0, 0] > 0.99
    # numbering clockwise flips the normal: z points down
    assert virtual_base(layout[::-1])[2, 2] < -0.99


def test_virtual_base_refuses_degenerate_markers():
    line = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]])
    with pytest.raises(GraphcalError, match="collinear"):
        virtual_base(line)
    with pytest.raises(GraphcalError, match="shape"):
        virtual_base(np.zeros((3, 3)))


def test_virtual_base_covariance_matches_monte_carlo():
    rng = np.random.default_rng(5)
    layout = a1_body_marker_layout()
    sigma = 0.001
    C = virtual_base_covariance(layout, sigma)
    T0 = virtual_base(layout)
    noisy = layout[None] + rng.normal(scale=sigma, size=(4000, 4, 3))
    Ts = virtual_base(noisy)
    xi = np.array([_log_right(T0, T) for T in Ts])
    C_mc = np.cov(xi.T)
    d = np.sqrt(np.diag(C))
    assert np.allclose(np.sqrt(np.diag(C_mc)), d, rtol=0.08)
    # and a foot point 0.3 m away inherits the rotation noise: compare with Monte Carlo too
    p_mocap = np.array([0.2, 0.15, -0.25])
    pv = vbase_points(Ts, np.broadcast_to(p_mocap, (len(Ts), 3)))
    Cp = point_covariance_in_vbase(vbase_points(T0[None], p_mocap[None]), C[None])[0]
    assert np.allclose(np.sqrt(np.diag(np.cov(pv.T))), np.sqrt(np.diag(Cp)), rtol=0.08)


# ----------------------------------------------------------------------------- identifiability
def test_identifiability_classifies_a_constructed_jacobian():
    rng = np.random.default_rng(1)
    a, b, c = rng.normal(size=(3, 200))
    # columns: a, b, 2a - b (aliased with a and b), c, zeros (no effect), c + tiny noise-level part
    A = np.column_stack([a, b, 2 * a - b, c, np.zeros(200)])
    rep = identifiability(A * 10.0, ["a", "b", "ab", "c", "dead"], np.ones(5))
    assert rep["c"].status == "identifiable" and rep["c"].free
    assert rep["dead"].status == "unidentifiable" and not rep["dead"].free
    for n in ("a", "b", "ab"):
        assert rep[n].status == "combination" and rep[n].structural
    assert rep.rank == 3 and sum(rep[n].free for n in ("a", "b", "ab")) == 2
    combo = dict(rep["ab"].combination)
    # ab = 2a - b: moving ab by +1 is undone by a -> +0.5 ... direction (1, -2 * 0.5...) in any
    # scaling: A @ w = 0 for the reported direction
    w = np.array([combo.get(n, 0.0) for n in ("a", "b", "ab", "c", "dead")])
    assert np.linalg.norm(A @ w) < 1e-9 * np.linalg.norm(A)
    assert abs(w[2]) == 1.0 and abs(w[0]) > 0.1 and abs(w[1]) > 0.1


def test_identifiability_scales_choose_the_nuisance_and_threshold_is_noise_level():
    rng = np.random.default_rng(2)
    x = rng.normal(size=100)
    # two parameters with the same effect: the one with the larger a-priori scale stays free
    rep = identifiability(100 * np.column_stack([x, x]), ["joint", "pose"], [0.03, 1.0])
    assert rep["pose"].free and not rep["joint"].free
    assert rep["joint"].status == rep["pose"].status == "combination" and rep["joint"].structural
    assert dict(rep["joint"].combination)["pose"] == pytest.approx(-1.0)
    # an effect below s_min noise sigmas over the whole data set is not identifiable
    small = identifiability(np.column_stack([x * 0.01]), ["weak"], [1.0])
    assert small["weak"].status == "unidentifiable"


@pytest.fixture(scope="module")
def yuan_like():
    """A1 left-front leg, 400 samples, gaussian noise, noisy body markers, hip offset 0 (so the
    generic SE(3) run has a fair truth for every free parameter)."""
    pert = LegPerturbation({"fl_thigh_joint": 1.5 * DEG, "fl_calf_joint": -2.0 * DEG},
                           {"fl_thigh_joint": (0.0, 0.004, 0.0), "fl_calf_joint": (0.0, 0.0, -0.010),
                            "fl_foot_joint": (0.0, 0.0, 0.015)})
    T_err = pose_from_xyz_rpy([0.002, -0.001, 0.005], [0.5 * DEG, -0.3 * DEG, 3.0 * DEG])
    sim = simulate_mocap("a1", feet=(FOOT,), n_samples=400, perturbation=pert, joint_noise_rad=0.2 * DEG,
                         marker_noise_m=0.0005, noise="gaussian", body_marker_noise_m=0.0005, T_layout_error=T_err,
                         p_foot_marker={FOOT: [0.0, 0.0, 0.02]}, seed=11)
    return sim, pert


def test_identify_recovers_injected_errors_within_3_sigma(yuan_like):
    sim, pert = yuan_like
    opts = IdentifyOptions(sigma_marker_m=0.0005, sigma_joint_rad=0.2 * DEG, scale_covariance=False)
    res = identify_legs_dataset(sim.dataset, options=opts, sigma_body_marker_m=0.0005)
    assert res.frame == "vbase" and res.converged
    rep = res.identifiability
    # the first joint's offset and position are aliased with the virtual base pose; the rest is identifiable
    assert rep["fl_hip_joint.offset_rad"].status == "combination" and rep["fl_hip_joint.offset_rad"].structural
    assert dict(rep["fl_hip_joint.offset_rad"].combination)["T_body_vbase.rx"] == pytest.approx(1.0, abs=0.01)
    for a in "xyz":
        p = rep[f"fl_hip_joint.d{a}_m"]
        assert p.status == "combination" and not p.free
        assert dict(p.combination)[f"T_body_vbase.{a}"] == pytest.approx(1.0, abs=0.01)
    truth = theta_from_perturbation(res.models[FOOT], pert)
    checked = 0
    for p, t in zip(res.legs[FOOT], truth):
        if p.status == "identifiable":
            assert p.free and p.sigma > 0
            assert abs(p.value - t) < 3 * p.sigma, (p.name, p.value, t, p.sigma)
            checked += 1
    assert checked == 5
    xi = _log_right(res.T_body_mocap, sim.T_body_mocap_true)
    s = np.sqrt(np.diag(res.T_body_mocap_covariance))
    assert np.all(np.abs(xi) < 3 * s), (xi, s)
    # honest noise model: the residual is at the noise level, far below the nominal error
    assert 0.85 < res.sigma0 < 1.15
    r = res.residuals[0]
    assert r.rmse_before_mm > 5 * r.rmse_after_mm
    assert r.rmse_nominal_mm is not None and r.rmse_nominal_mm > r.rmse_before_mm


def test_identify_yuans_parameter_set_and_noise_free_exactness():
    """Yuan's setting (pose free only in yaw and z, no hip position): with noise-free data the
    identification hits the truth to round-off, in a few LM iterations from the nominal start."""
    pert = LegPerturbation({"fl_hip_joint": 1.0 * DEG, "fl_thigh_joint": 1.5 * DEG, "fl_calf_joint": 2.0 * DEG},
                           {"fl_thigh_joint": (0, 0.0038, 0), "fl_calf_joint": (0, 0, -0.01), "fl_foot_joint": (0, 0, -0.02)})
    sim = simulate_mocap("a1", feet=(FOOT,), n_samples=60, perturbation=pert,
                         T_layout_error=pose_from_xyz_rpy([0, 0, 0.005], [0, 0, 3.0 * DEG]), seed=4)
    data = mocap_data_from_dataset(sim.dataset)
    res = identify_legs(data.robot, data.tracks, options=IdentifyOptions(mocap_free=("rz", "z"), origins="none"),
                        T_body_mocap_nominal=data.T_body_mocap_nominal, frame=data.frame)
    truth = theta_from_perturbation(res.models[FOOT], pert)
    assert all(p.status == "identifiable" for p in res.identifiability.parameters)
    assert np.allclose(res.theta[FOOT], truth, atol=1e-9)
    rz = [p for p in res.mocap if p.name == "T_body_vbase.rz"][0]
    z = [p for p in res.mocap if p.name == "T_body_vbase.z"][0]
    assert rz.value == pytest.approx(3.0 * DEG, abs=1e-9) and z.value == pytest.approx(0.005, abs=1e-9)
    assert [p.status for p in res.mocap if p.name.endswith(("rx", "ry", ".x", ".y"))] == ["known"] * 4
    assert res.residuals[0].rmse_after_mm < 1e-6 and res.iterations <= 8


@pytest.mark.parametrize("n_samples, warned", [(3, True), (60, False)])
def test_a_fit_without_redundancy_is_warned_about(n_samples, warned):
    """3 samples of one foot marker: 9 coordinates for 9 unknowns, an exact fit (before: a calf
    offset 18 sigma off the truth and no warning). 60 samples: 180 coordinates, no warning."""
    pert = LegPerturbation({"fl_calf_joint": 2.0 * DEG}, {"fl_calf_joint": (0, 0, -0.01)})
    sim = simulate_mocap("a1", feet=(FOOT,), n_samples=n_samples, perturbation=pert, joint_noise_rad=0.1 * DEG,
                         marker_noise_m=0.0005, noise="gaussian", seed=5)
    data = mocap_data_from_dataset(sim.dataset)
    res = identify_legs(data.robot, data.tracks, T_body_mocap_nominal=data.T_body_mocap_nominal, frame=data.frame)
    hits = [w for w in res.warnings if "residual degree(s) of freedom" in w]
    assert bool(hits) == warned, res.warnings
    if warned:
        assert res.dof < 10 and f"only {res.dof} residual" in hits[0]


def test_unknown_marker_makes_the_last_links_aliased(yuan_like):
    sim, _ = yuan_like
    from dataclasses import replace

    ds = replace(sim.dataset, mocap_markers={k: v for k, v in sim.dataset.mocap_markers.items() if k != FOOT})
    data = mocap_data_from_dataset(ds, sigma_body_marker_m=0.0005)
    assert data.tracks[0].p_foot_marker is None and data.tracks[0].cov_extra is not None
    res = identify_legs(data.robot, data.tracks, options=IdentifyOptions(sigma_marker_m=0.0005, sigma_joint_rad=0.2 * DEG),
                        T_body_mocap_nominal=data.T_body_mocap_nominal, frame=data.frame)
    rep = res.identifiability
    # the last joint's offset turns the marker about the knee axis; the shank length and the
    # lateral offset move it along the foot's z and y: all exactly aliased with the marker position
    for name, axis in (("fl_calf_joint.offset_rad", "x"), ("fl_foot_joint.delta_m", "z"), ("fl_thigh_joint.delta_m", "y")):
        p = rep[name]
        assert p.status == "combination" and p.structural and not p.free, name
        assert f"{FOOT}.p_foot_marker.{axis}" in dict(p.combination), (name, p.combination)
    assert rep[f"{FOOT}.p_foot_marker.x"].free
    assert 0.85 < res.sigma0 < 1.15  # the fit still reaches the noise
    # without the virtual base's uncertainty (0.5 mm body markers) the residuals exceed the noise model
    plain = mocap_data_from_dataset(ds)
    res0 = identify_legs(plain.robot, plain.tracks, options=IdentifyOptions(sigma_marker_m=0.0005, sigma_joint_rad=0.2 * DEG),
                         T_body_mocap_nominal=plain.T_body_mocap_nominal, frame=plain.frame)
    assert res0.sigma0 > 1.15


# ----------------------------------------------------------------------------- dataset errors
def test_mocap_data_errors(yuan_like, tmp_path):
    sim, _ = yuan_like
    from dataclasses import replace

    from graphcal.io.dataset import Table

    m = sim.dataset.mocap
    no_b4 = m.select(m["marker"] != "body.4")
    with pytest.raises(DatasetError, match=r"mocap\.csv.*column marker.*all four body markers"):
        mocap_data_from_dataset(replace(sim.dataset, mocap=no_b4))
    only_body = m.select(np.char.startswith(m["marker"].astype(str), "body."))
    with pytest.raises(DatasetError, match="at least one marker on a foot"):
        mocap_data_from_dataset(replace(sim.dataset, mocap=only_body))
    with pytest.raises(DatasetError, match=r"mocap\.csv.*file.*missing"):
        mocap_data_from_dataset(replace(sim.dataset, mocap=None))
    assert isinstance(m, Table)


# ----------------------------------------------------------------------------- command line
def _run(*args):
    return subprocess.run([sys.executable, "-m", "graphcal", *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def cli_dataset(tmp_path_factory):
    pert = LegPerturbation({"fl_thigh_joint": 1.0 * DEG}, {"fl_calf_joint": (0.0, 0.0, -0.012)})
    sim = simulate_mocap("a1", feet=(FOOT,), n_samples=150, perturbation=pert, joint_noise_rad=0.1 * DEG,
                         marker_noise_m=0.0005, noise="gaussian", body_markers=False, seed=8)
    out = tmp_path_factory.mktemp("mocap") / "a1_mocap"
    write_mocap_simulation(sim, out)
    return out, sim, pert


def test_cli_identify_legs_writes_the_files(cli_dataset, tmp_path):
    ds, sim, pert = cli_dataset
    assert (ds / "truth.yaml").is_file()
    out = tmp_path / "legs_out"
    proc = _run("identify-legs", ds, "--out", out, "--quiet", "--sigma-marker-mm", "0.5")
    assert proc.returncode == 0, proc.stderr
    assert "fl_foot: marker RMSE" in proc.stdout
    doc = yaml.safe_load((out / "legs.yaml").read_text())
    assert doc["format"] == "graphcal-legs/1"
    legs = doc["legs"]
    assert set(legs) == {FOOT}
    for name, v in legs[FOOT].items():
        assert {"value", "sigma", "sigma_model", "sigma_jackknife", "significance"} <= set(v)
        assert isinstance(v["value"], float) and v["sigma"] > 0
        # the governing sigma is the larger of the model and the jackknife sigma (issue 27)
        assert v["sigma"] == max(v["sigma_model"], v["sigma_jackknife"])
    # the verdict comes first on the console and in the file, judged against the declared 0.5 mm
    assert proc.stdout.splitlines()[0].startswith(("adequacy: fits", "WARNING: adequacy:"))
    assert doc["adequacy"]["verdict"] in ("fits", "does not fit") and list(doc)[3] == "adequacy"
    assert "command line" in doc["adequacy"]["judged_against"]["source"]
    # the injected errors, within 4 sigma (the covariance is scaled by the a-posteriori variance factor)
    for name, true in (("fl_thigh_joint.offset_rad", 1.0 * DEG), ("fl_calf_joint.delta_m", 0.012)):
        v = legs[FOOT][name]
        assert abs(v["value"] - true) < 4 * v["sigma"], (name, v, true)
    assert doc["identifiability"]["parameters"]["fl_hip_joint.offset_rad"]["status"] == "combination"
    assert doc["foot_error_mm"][FOOT]["rmse_after"] < 0.3 * doc["foot_error_mm"][FOOT]["rmse_before"]
    # the URDF reproduces the identified kinematics
    robot = load_robot(model="a1")
    cal = load_robot(out / "robot_calibrated.urdf", base_frame="body", feet=(FOOT,))
    from graphcal.models.legs import leg_model

    m = leg_model(robot, FOOT)
    theta = np.array([legs[FOOT].get(n, {"value": 0.0})["value"] for n in m.names])
    q = np.array([[0.1, 0.7, -1.5], [-0.3, 1.2, -2.0]])
    p = point_kinematics(robot.leg(FOOT), m, q, theta).p_base_point
    assert np.allclose(p, [cal.fk_pinocchio(FOOT, qq)[:3, 3] for qq in q], atol=1e-12)
    html = (out / "report.html").read_text()
    assert "<img" in html and "fl_hip_joint.offset_rad" in html
    # the verdict is the report's first section
    assert html.index("Model adequacy") < html.index("Foot marker error") < html.index("Leg parameters")
    from graphcal.report.page import CSS

    assert CSS in html  # the one page template and style sheet of every report
    png = out / "foot_errors_fl_foot.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(doc["output_files"]) == {p.name for p in out.iterdir()}


def test_cli_bad_input_is_exit_2_naming_file_and_field(cli_dataset, tmp_path, capsys):
    from graphcal.cli import main

    ds, _, _ = cli_dataset
    bad = tmp_path / "bad"
    shutil.copytree(ds, bad)
    lines = (bad / "mocap.csv").read_text().splitlines()
    cells = lines[3].split(",")
    cells[3] = "1.2.3"  # column y of data row 3
    lines[3] = ",".join(cells)
    (bad / "mocap.csv").write_text("\n".join(lines) + "\n")
    assert main(["identify-legs", str(bad), "--out", str(tmp_path / "o1"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "mocap.csv" in err and "column y" in err and "row 3" in err and "Traceback" not in err
    assert not (tmp_path / "o1").exists()
    # no mocap.csv at all
    (bad / "mocap.csv").unlink()
    assert main(["identify-legs", str(bad), "--out", str(tmp_path / "o2"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "mocap.csv" in err and "missing" in err
    # an output folder with someone else's files is refused before any work
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    assert main(["identify-legs", str(ds), "--out", str(mine), "--quiet"]) == 2
    assert "notes.txt" in capsys.readouterr().err and (mine / "notes.txt").read_text() == "precious"
    assert main(["identify-legs", str(ds), "--out", str(tmp_path / "o3"), "--quiet", "--mocap-free", "yaw"]) == 2
    assert "--mocap-free" in capsys.readouterr().err


def test_a_previous_identification_of_either_format_id_may_be_replaced(tmp_path):
    """legs.yaml has its own format id now; a folder written with the old one (graphcal-calibration/1)
    is still recognised as a previous identify-legs output, anything else is refused."""
    from graphcal.io.atomic import OutputExistsError
    from graphcal.report.legs_output import check_output_folder

    for fmt in ("graphcal-legs/1", "graphcal-calibration/1"):
        out = tmp_path / fmt.replace("/", "_")
        out.mkdir()
        (out / "legs.yaml").write_text(f"format: {fmt}\n")
        (out / "report.html").write_text("<html></html>")
        check_output_folder(out)
    out = tmp_path / "other"
    out.mkdir()
    (out / "legs.yaml").write_text("format: something-else/1\n")
    with pytest.raises(OutputExistsError):
        check_output_folder(out)


def test_the_identifiability_threshold_is_three_sigma_of_the_noise():
    """A parameter whose effect on the residuals is 2 sigma in total is unidentifiable, 4 sigma
    identifiable (S_MIN = 3)."""
    from graphcal.legs.identifiability import identifiability

    u = np.random.default_rng(2).normal(size=100)
    u /= np.linalg.norm(u)
    assert identifiability(np.c_[2.0 * u], ["p"], [1.0])["p"].status == "unidentifiable"
    assert identifiability(np.c_[4.0 * u], ["p"], [1.0])["p"].status == "identifiable"
