"""Every malformed-dataset case of docs/dataset.md: one DatasetError naming the file and the row or key.

Each case copies the hand-made fixture tests/data/octopus_small, breaks one thing, and checks the
exception type, the file named, the row/column/key named and a fragment of what was expected.
"""

from __future__ import annotations

import csv
import io
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from graphcal.errors import DatasetError
from graphcal.io import read_dataset, read_ply, validate_dataset, write_ply

FIXTURE = Path(__file__).parent / "data" / "octopus_small"


# ------------------------------------------------------------------ mutation helpers
def yaml_replace(old: str, new: str):
    def f(d: Path):
        text = (d / "dataset.yaml").read_text()
        assert old in text, old
        (d / "dataset.yaml").write_text(text.replace(old, new, 1))

    return f


def _rows(path: Path) -> list[list[str]]:
    return list(csv.reader(io.StringIO(path.read_text(), newline="")))


def _write_rows(path: Path, rows) -> None:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    path.write_text(buf.getvalue())


def set_cell(file: str, row: int, column: str, value: str):
    """row: 1-based data row."""
    return set_cells(file, row, {column: value})


def set_cells(file: str, row: int, values: dict):
    """row: 1-based data row; values: column -> text."""

    def f(d: Path):
        rows = _rows(d / file)
        for column, value in values.items():
            rows[row][rows[0].index(column)] = value
        _write_rows(d / file, rows)

    return f


def drop_column(file: str, column: str):
    def f(d: Path):
        rows = _rows(d / file)
        j = rows[0].index(column)
        _write_rows(d / file, [r[:j] + r[j + 1 :] for r in rows])

    return f


def add_column(file: str, column: str, value: str):
    def f(d: Path):
        rows = _rows(d / file)
        _write_rows(d / file, [rows[0] + [column]] + [r + [value] for r in rows[1:]])

    return f


def rename_column(file: str, old: str, new: str):
    def f(d: Path):
        rows = _rows(d / file)
        rows[0][rows[0].index(old)] = new
        _write_rows(d / file, rows)

    return f


def header_only(rel: str):
    def f(d: Path):
        _write_rows(d / rel, _rows(d / rel)[:1])

    return f


def semicolon_separated(rel: str):
    """The file as a spreadsheet in a comma-decimal locale exports it: ';' between the cells."""

    def f(d: Path):
        rows = _rows(d / rel)
        (d / rel).write_text("\n".join(";".join(r) for r in rows) + "\n")

    return f


def write_file(rel: str, content: str | bytes):
    def f(d: Path):
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(content if isinstance(content, bytes) else content.encode())

    return f


def remove(rel: str):
    def f(d: Path):
        p = d / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()

    return f


def symlink(rel: str, target_outside: str):
    def f(d: Path):
        outside = d.parent / target_outside
        shutil.copyfile(d / "clouds" / "depth" / "1.ply", outside)
        p = d / rel
        if p.exists():
            p.unlink()
        os.symlink(outside, p)

    return f


def chain(*fs):
    def f(d: Path):
        for g in fs:
            g(d)

    return f


def cloud_points(rel: str, points):
    def f(d: Path):
        write_ply(d / rel, np.asarray(points, dtype=float))

    return f


# ------------------------------------------------------------------ the cases
# (id, mutation, file named, fragments that must appear in the message)
Y = "dataset.yaml"
S = "stations.csv"
T = "timeseries.csv"
P = "planes.csv"
M = "mocap.csv"
NOT_UNIT_QUAT = "0.9,0.3,0.1,0.1"
CASES = [
    # dataset.yaml
    ("yaml-missing", remove(Y), Y, ["dataset.yaml", "missing"]),
    ("yaml-syntax", yaml_replace("type: depth_camera", "type: [depth_camera"), Y, ["line ", "valid YAML"]),
    ("yaml-not-utf8", write_file(Y, b"format: graphcal-dataset/1\nrobot: \xff\xfe\n"), Y, ["line 2", "UTF-8"]),
    ("yaml-duplicate-key", yaml_replace("ground:", "sensors: {}\nground:"), Y, ["line ", "duplicate key 'sensors'"]),
    ("yaml-not-mapping", write_file(Y, "- a\n- b\n"), Y, ["top level", "a mapping"]),
    ("format-wrong", yaml_replace("format: graphcal-dataset/1", "format: graphcal-dataset/2"), Y, ["format", "graphcal-dataset/2"]),
    ("format-missing", yaml_replace("format: graphcal-dataset/1", ""), Y, ["format", "missing"]),
    ("robot-base-missing", yaml_replace("  base_frame: body\n", ""), Y, ["robot.base_frame", "missing"]),
    ("robot-feet-missing", yaml_replace("  feet: [lf_foot, lm_foot, lr_foot, rf_foot, rm_foot, rr_foot]\n", ""),
     Y, ["robot.feet", "missing"]),
    ("robot-no-source", yaml_replace("  model: octopus              # a built-in robot model of graphcal\n", ""),
     Y, ["robot", "exactly one of", "neither"]),
    ("robot-two-sources", yaml_replace("  model: octopus", "  urdf: robot.urdf\n  model: octopus"), Y, ["robot", "both"]),
    ("robot-unknown-key", yaml_replace("  base_frame: body", "  base_frame: body\n  foot: [x]"), Y,
     ["robot.foot", "unknown key"]),
    ("robot-model-unknown", yaml_replace("model: octopus", "model: octopuz"), Y, ["robot.model", "octopuz"]),
    ("robot-base-absent", yaml_replace("base_frame: body", "base_frame: torso"), Y, ["robot.base_frame", "torso"]),
    ("robot-foot-absent", yaml_replace("[lf_foot, lm_foot", "[lf_toe, lm_foot"), Y, ["robot.feet[0]", "lf_toe"]),
    ("robot-foot-not-below", yaml_replace("base_frame: body", "base_frame: lf_femur"), Y,
     ["robot.feet", "below the base frame", "lm_foot"]),
    ("robot-foot-twice", yaml_replace("[lf_foot, lm_foot", "[lf_foot, lf_foot"), Y, ["robot.feet[1]", "once"]),
    ("urdf-absolute", yaml_replace("model: octopus", "urdf: /etc/robot.urdf"), Y, ["robot.urdf", "absolute"]),
    ("urdf-escapes", yaml_replace("model: octopus", "urdf: ../robot.urdf"), Y, ["robot.urdf", "inside the dataset"]),
    ("urdf-missing", yaml_replace("model: octopus", "urdf: robot.urdf"), Y, ["robot.urdf", "no such file"]),
    ("urdf-symlink-out", chain(yaml_replace("model: octopus", "urdf: robot.urdf"), symlink("robot.urdf", "x.urdf")),
     Y, ["robot.urdf", "inside the dataset"]),
    ("urdf-invalid", chain(yaml_replace("model: octopus", "urdf: robot.urdf"), write_file("robot.urdf", "<robot")),
     Y, ["robot.urdf", "XML"]),
    ("urdf-is-sdf", chain(yaml_replace("model: octopus", "urdf: robot.urdf"),
                          write_file("robot.urdf", "<sdf version='1.6'><model name='x'><link name='body'/></model></sdf>")),
     Y, ["robot.urdf", "root element is <sdf>"]),
    ("sensor-type-missing", yaml_replace("    type: depth_camera\n", ""), Y, ["sensors.depth.type", "missing"]),
    ("sensor-type-bad", yaml_replace("type: depth_camera", "type: kinect"), Y,
     ["sensors.depth.type", "depth_camera, laser_scanner, stereo_camera", "kinect"]),
    ("sensor-name-bad", yaml_replace("  depth:", "  'dep/th':"), Y, ["sensors.dep/th", "sensor name"]),
    ("prior-missing", yaml_replace("T_body_sensor_prior:", "T_body_sensor_priors:"), Y,
     ["sensors.depth.T_body_sensor_prior", "missing"]),
    ("prior-unknown-key", yaml_replace("rpy_deg: [-90.0", "rpy: [-1.57, 0, 0]\n      rpy_deg: [-90.0"), Y,
     ["sensors.depth.T_body_sensor_prior.rpy", "unknown key"]),
    ("prior-xyz-2", yaml_replace("xyz: [0.30, 0.0, 0.40]", "xyz: [0.30, 0.0]"), Y,
     ["sensors.depth.T_body_sensor_prior.xyz", "3 numbers"]),
    ("prior-rpy-text", yaml_replace("[-90.0, 0.0, -120.0]", "[-90.0, zero, -120.0]"), Y,
     ["sensors.depth.T_body_sensor_prior.rpy_deg[1]", "a number"]),
    ("prior-rpy-inf", yaml_replace("[-90.0, 0.0, -120.0]", "[-90.0, .inf, -120.0]"), Y,
     ["T_body_sensor_prior.rpy_deg[1]", "finite"]),
    ("prior-rpy-range", yaml_replace("[-90.0, 0.0, -120.0]", "[-90.0, 0.0, 720]"), Y,
     ["sensors.depth.T_body_sensor_prior.rpy_deg[2]", "[-360, 360]"]),
    ("prior-sigma-negative", yaml_replace("sigma_mm: 50", "sigma_mm: -50"), Y,
     ["sensors.depth.T_body_sensor_prior.sigma_mm", ">= 0"]),
    ("prior-sigma-bool", yaml_replace("sigma_rpy_deg: 5", "sigma_rpy_deg: yes"), Y,
     ["T_body_sensor_prior.sigma_rpy_deg", "a number"]),
    ("prior-millimetres", yaml_replace("xyz: [0.30, 0.0, 0.40]", "xyz: [300, 0, 400]"), Y,
     ["sensors.depth.T_body_sensor_prior.xyz", "looks like millimetres; the contract uses metres"]),
    ("imu-prior-missing", yaml_replace("  T_body_imu_prior:", "  T_imu_prior:"), Y, ["imu.T_body_imu_prior", "missing"]),
    ("marker-link-absent", yaml_replace("ground:", "mocap: {markers: {tool: {link: lf_hand}}}\nground:"), Y,
     ["mocap.markers.tool.link", "lf_hand"]),
    ("marker-unknown-key", yaml_replace("ground:", "mocap: {markers: {tool: {link: lf_foot, pos: [0, 0, 0]}}}\nground:"),
     Y, ["mocap.markers.tool.pos", "unknown key"]),
    # which files
    ("no-stations-no-timeseries", chain(remove(S), remove(T), remove(P), remove(M), remove("clouds")), "octopus_",
     ["stations.csv or timeseries.csv"]),
    # stations.csv
    ("stations-empty", write_file(S, ""), S, ["header", "column names"]),
    ("stations-semicolons", semicolon_separated(S), S, ["header", "separated by commas (this file uses semicolons"]),
    ("stations-header-only", header_only(S), P, ["column station", "(stations.csv has a header but no rows)"]),
    ("stations-no-station", drop_column(S, "station"), S, ["column station", "required"]),
    ("stations-unknown-column", add_column(S, "temperature", "20"), S, ["column temperature", "unknown column"]),
    ("stations-contact-not-allowed", add_column(S, "contact_lf_foot", "1"), S, ["column contact_lf_foot"]),
    ("stations-duplicate-header", rename_column(S, "time", "session"), S, ["header, column 3", "once"]),
    ("stations-body-incomplete", drop_column(S, "body_qz"), S, ["column body_qz", "all of body_x"]),
    ("stations-imu-incomplete", drop_column(S, "imu_gy"), S, ["column imu_gy", "all of imu_gx"]),
    ("stations-text-cell", set_cell(S, 2, "q_lf_coxa_joint", "abc"), S,
     ["row 2 (line 3), column q_lf_coxa_joint", "a number", "abc"]),
    ("stations-nan", set_cell(S, 2, "q_lm_femur_joint", "nan"), S, ["row 2 (line 3), column q_lm_femur_joint", "finite"]),
    ("stations-inf", set_cell(S, 3, "time", "-inf"), S, ["row 3 (line 4), column time", "finite"]),
    ("stations-overflow", set_cell(S, 1, "imu_ax", "1e400"), S, ["row 1 (line 2), column imu_ax", "overflows"]),
    ("stations-empty-cell", set_cell(S, 4, "body_x", ""), S, ["row 4 (line 5), column body_x", "empty cell"]),
    ("stations-underscore", set_cell(S, 4, "body_x", "1_0"), S, ["row 4 (line 5), column body_x", "a number"]),
    ("stations-empty-session", set_cell(S, 2, "session", ""), S, ["row 2 (line 3), column session", "label"]),
    ("stations-duplicate-id", set_cell(S, 3, "station", "1"), S, ["row 3 (line 4), column station", "unique", "row 1"]),
    ("stations-non-integer-id", set_cell(S, 2, "station", "2.5"), S, ["row 2 (line 3), column station", "integer"]),
    ("stations-ragged", write_file(S, "station,time\n1,0.5\n2,1.5,7\n"), S, ["row 2 (line 3)", "2 cells", "3 cells"]),
    ("stations-bad-quote", write_file(S, 'station,session\n1,"a"b\n'), S, ["line 2", "CSV"]),
    ("stations-quaternion", set_cell(S, 2, "body_qw", "1.2"), S, ["row 2 (line 3), column body_qw..body_qz",
                                                                   "unit quaternion", "norm 1.2"]),
    ("stations-body-mm", set_cell(S, 3, "body_z", "680"), S, ["row 3 (line 4), column body_z",
                                                              "looks like millimetres; the contract uses metres"]),
    ("stations-joint-absent", rename_column(S, "q_lf_coxa_joint", "q_lf_hip_joint"), S,
     ["column q_lf_hip_joint", "a moving joint of the URDF"]),
    ("stations-tau-absent", add_column(S, "tau_lf_hip", "0.5"), S, ["column tau_lf_hip", "a moving joint"]),
    ("stations-joint-missing", drop_column(S, "q_rr_tibia_joint"), S, ["column q_rr_tibia_joint", "missing"]),
    ("stations-imu-in-g", chain(*[set_cell(S, r, "imu_az", "1.0") for r in (1, 2, 3, 4)]), S,
     ["column imu_ax..imu_az", "units of g"]),
    ("stations-q-without-robot", chain(yaml_replace("robot:", "robot: null\nxrobot:"), remove(T), remove(M),
                                                   remove("clouds/depth/t10.01.ply")), S,
     ["column q_lf_coxa_joint", "a robot in dataset.yaml"]),
    ("stations-not-utf8", write_file(S, b"station,time\n1,0.5\n2,\xe9\n"), S, ["line 3", "UTF-8"]),
    # timeseries.csv
    ("ts-no-time", drop_column(T, "time"), T, ["column time", "required"]),
    ("ts-station-column", add_column(T, "station", "1"), T, ["column station", "stations.csv"]),
    ("ts-time-backwards", set_cell(T, 3, "time", "9.0"), T, ["row 3 (line 4), column time", "never decrease"]),
    ("ts-contact-value", set_cell(T, 2, "contact_lf_foot", "1.5"), T, ["row 2 (line 3), column contact_lf_foot",
                                                                       "0 or 1"]),
    ("ts-contact-foot", rename_column(T, "contact_rf_foot", "contact_rf_toe"), T, ["column contact_rf_toe",
                                                                                   "robot.feet"]),
    ("ts-cloud-sensor", rename_column(T, "cloud_depth", "cloud_lidar"), T, ["column cloud_lidar", "a sensor"]),
    ("ts-cloud-absolute", set_cell(T, 1, "cloud_depth", "/tmp/x.ply"), T, ["row 1 (line 2), column cloud_depth",
                                                                           "absolute"]),
    ("ts-cloud-escapes", set_cell(T, 1, "cloud_depth", "clouds/../../x.ply"), T,
     ["row 1 (line 2), column cloud_depth", "inside the dataset"]),
    ("ts-cloud-missing", set_cell(T, 3, "cloud_depth", "clouds/depth/t10.02.ply"), T,
     ["row 3 (line 4), column cloud_depth", "no such file"]),
    ("ts-cloud-symlink-out", symlink("clouds/depth/t10.01.ply", "outside.ply"), T,
     ["row 2 (line 3), column cloud_depth", "inside the dataset"]),
    ("ts-body-mm", chain(*[add_column(T, c, v) for c, v in zip(
        ["body_x", "body_y", "body_z", "body_qw", "body_qx", "body_qy", "body_qz"],
        ["0", "0", "680", "1", "0", "0", "0"])]), T, ["row 1 (line 2), column body_z", "millimetres"]),
    # planes.csv
    ("planes-missing-column", drop_column(P, "nz"), P, ["column nz", "required"]),
    ("planes-unknown-column", add_column(P, "score", "1"), P, ["column score", "unknown column"]),
    ("planes-cov-incomplete", drop_column(P, "cov_21"), P, ["column cov_21", "all of cov_00"]),
    ("planes-normal", set_cell(P, 2, "nz", "-0.9"), P, ["row 2 (line 3), column nx..nz", "unit normal", "norm 1.08"]),
    ("planes-d-negative", set_cell(P, 3, "d", "-0.9"), P, ["row 3 (line 4), column d", "d >= 0"]),
    ("planes-d-mm", set_cell(P, 1, "d", "900"), P, ["row 1 (line 2), column d", "looks like millimetres"]),
    ("planes-station", set_cell(P, 4, "station", "7"), P, ["row 4 (line 5), column station", "stations.csv", "7"]),
    ("planes-sensor", set_cell(P, 2, "sensor", "lidar"), P, ["row 2 (line 3), column sensor", "dataset.yaml", "lidar"]),
    ("planes-n-points", set_cell(P, 1, "n_points", "-3"), P, ["row 1 (line 2), column n_points", ">= 0"]),
    ("planes-rms", set_cell(P, 1, "rms", "-0.1"), P, ["row 1 (line 2), column rms", ">= 0"]),
    ("planes-cov-asym", set_cell(P, 2, "cov_01", "5e-7"), P, ["row 2 (line 3), column cov_00..cov_33", "symmetric"]),
    ("planes-cov-diag", set_cell(P, 2, "cov_22", "-1e-6"), P, ["row 2 (line 3), column cov_00..cov_33", "variances"]),
    ("planes-cov-zero", set_cells(P, 2, {f"cov_{i}{j}": "0" for i in range(4) for j in range(4)}), P,
     ["row 2 (line 3), column cov_00..cov_33", "full rank 3 across the plane", "leave out the cov_ columns"]),
    ("planes-cov-indefinite", set_cells(P, 2, {f"cov_{i}{j}": "1e-6" if i == j else "5e-6"
                                               for i in range(4) for j in range(4)}), P,
     ["row 2 (line 3), column cov_00..cov_33", "positive semi-definite", "eigenvalue of -4e-06"]),
    ("planes-without-stations", chain(remove(S), remove(M), remove("clouds/depth/1.ply")), P,
     ["row 1 (line 2), column station", "no stations.csv"]),
    # mocap.csv
    ("mocap-missing-column", drop_column(M, "marker"), M, ["column marker", "required"]),
    ("mocap-unknown-column", add_column(M, "residual", "0"), M, ["column residual", "unknown"]),
    ("mocap-mm", set_cell(M, 3, "x", "300"), M, ["row 3 (line 4), column x", "looks like millimetres"]),
    ("mocap-marker-name", set_cell(M, 5, "marker", "hand"), M, ["row 5 (line 6), column marker", "hand"]),
    ("mocap-body-no-index", set_cell(M, 1, "marker", "body"), M, ["row 1 (line 2), column marker", "body.1"]),
    ("mocap-time", set_cell(M, 6, "time", "0.75"), M, ["row 6 (line 7), column time", "the time of a station"]),
    ("mocap-duplicate", set_cell(M, 2, "marker", "body.1"), M, ["row 2 (line 3), column marker", "once per time"]),
    # clouds
    ("cloud-unknown-sensor", write_file("clouds/lidar/1.ply", "ply\n"), "clouds/lidar", ["sensor of dataset.yaml"]),
    ("cloud-unknown-station", cloud_points("clouds/depth/99.ply", [[0, 0, 1]]), "clouds/depth/99.ply",
     ["station id of stations.csv", "no such station"]),
    ("cloud-bad-name", cloud_points("clouds/depth/first.ply", [[0, 0, 1]]), "clouds/depth/first.ply",
     ["<station>.ply"]),
    ("cloud-two-for-one-station", cloud_points("clouds/depth/001.ply", [[0, 0, 1]]), "clouds/depth/",
     ["one cloud per station"]),
    ("cloud-symlink-out", symlink("clouds/depth/1.ply", "outside.ply"), "clouds/depth/1.ply", ["inside the dataset"]),
    ("cloud-symlink-loop", lambda d: os.symlink("loop.ply", d / "clouds" / "depth" / "loop.ply"),
     "clouds/depth/loop.ply", ["inside the dataset"]),
    ("cloud-folder-symlink-out", lambda d: ((d / "timeseries.csv").unlink(),  # its clouds are checked first
                                            shutil.move(d / "clouds" / "depth", d.parent / "depth_outside"),
                                            os.symlink(d.parent / "depth_outside", d / "clouds" / "depth")),
     "clouds/depth/", ["inside the dataset"]),
]


@pytest.fixture
def dataset_copy(tmp_path) -> Path:
    d = tmp_path / "octopus_small"
    shutil.copytree(FIXTURE, d, symlinks=True)
    return d


def test_fixture_is_valid(dataset_copy):
    report = validate_dataset(dataset_copy)
    assert report.n_stations == 4 and report.n_clouds == 2 and report.warnings == ()


@pytest.mark.parametrize("mutate, file, fragments", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_malformed_dataset_is_refused(dataset_copy, mutate, file, fragments):
    mutate(dataset_copy)
    with pytest.raises(DatasetError) as info:
        read_dataset(dataset_copy)
    msg = str(info.value)
    assert file in msg, msg
    assert file in str(info.value.file) or file.rstrip("/") in str(info.value.file), info.value.file
    for frag in fragments:
        assert frag in msg, (frag, msg)
    assert "Traceback" not in msg and "\n" not in msg
    # validate_dataset refuses it the same way
    with pytest.raises(DatasetError) as info2:
        validate_dataset(dataset_copy)
    assert str(info2.value) == msg


# ------------------------------------------------------------------ cloud contents (validate_dataset only)
PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
CLOUD_CASES = [
    ("ply-empty-file", write_file("clouds/depth/1.ply", ""), ["unreadable or empty PLY"]),
    ("ply-not-ply", write_file("clouds/depth/1.ply", "hello world\n"), ["unreadable or empty PLY"]),
    ("ply-zero-points", write_file("clouds/depth/1.ply", PLY_HEAD.format(n=0)), ["unreadable or empty PLY"]),
    ("ply-truncated-ascii", write_file("clouds/depth/1.ply", PLY_HEAD.format(n=3) + "0 0 1\n0 1\n"),
     ["body", "unreadable or empty PLY"]),
    ("ply-text-value", write_file("clouds/depth/1.ply", PLY_HEAD.format(n=1) + "0 zero 1\n"), ["a number", "'zero'"]),
    ("ply-nan", write_file("clouds/depth/1.ply", PLY_HEAD.format(n=2) + "0 0 1\n0 nan 1\n"),
     ["point 2 (1-based)", "finite"]),
    ("ply-millimetres", cloud_points("clouds/depth/1.ply", [[100, 200, 1500], [0, 0, 1200]]),
     ["looks like millimetres; the contract uses metres"]),
    ("ply-no-z", write_file("clouds/depth/1.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                            "property float y\nend_header\n0 0\n"), ["'z'"]),
]


@pytest.mark.parametrize("mutate, fragments", [c[1:] for c in CLOUD_CASES], ids=[c[0] for c in CLOUD_CASES])
def test_bad_cloud_is_refused_by_validate(dataset_copy, mutate, fragments):
    mutate(dataset_copy)
    read_dataset(dataset_copy)  # read_dataset does not open the PLY files (documented)
    with pytest.raises(DatasetError) as info:
        validate_dataset(dataset_copy)
    msg = str(info.value)
    assert "clouds/depth/1.ply" in msg and "\n" not in msg, msg
    for frag in fragments:
        assert frag in msg, (frag, msg)


def test_truncated_and_padded_binary_ply(tmp_path):
    pts = np.random.default_rng(0).normal(size=(20, 3))
    write_ply(tmp_path / "a.ply", pts)
    data = (tmp_path / "a.ply").read_bytes()
    for name, content in [("short.ply", data[:-5]), ("long.ply", data + b"\0" * 8),
                          ("huge.ply", data.replace(b"element vertex 20", b"element vertex 2000000000"))]:  # fmt: skip
        (tmp_path / name).write_bytes(content)
        with pytest.raises(DatasetError, match="unreadable or empty PLY") as info:
            read_ply(tmp_path / name)
        assert name in str(info.value)
    with pytest.raises(DatasetError, match="no such file"):
        read_ply(tmp_path / "missing.ply")


def test_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match="no such folder"):
        read_dataset(tmp_path / "nope")


def test_load_cloud_of_missing_station(dataset_copy):
    from graphcal.io import load_cloud

    ds = read_dataset(dataset_copy)
    assert load_cloud(ds, "depth", 1).shape == (4, 3)
    with pytest.raises(DatasetError, match="clouds/depth/2.ply"):
        load_cloud(ds, "depth", 2)


# ------------------------------------------------------------------ forward compatibility / decisions
def test_unknown_top_level_keys_are_kept(dataset_copy):
    yaml_replace("ground:", "calibration_notes: {by: someone, date: '2024-05-01'}\nground:")(dataset_copy)
    ds = read_dataset(dataset_copy)
    assert ds.extra == {"calibration_notes": {"by": "someone", "date": "2024-05-01"}}


def test_unknown_sensor_and_imu_keys_are_kept(dataset_copy):
    yaml_replace("    type: depth_camera", "    type: depth_camera\n    resolution: [640, 480]")(dataset_copy)
    yaml_replace("  T_body_imu_prior:", "  rate_hz: 400\n  T_body_imu_prior:")(dataset_copy)
    ds = read_dataset(dataset_copy)
    assert ds.sensors["depth"].extra == {"resolution": [640, 480]}
    assert ds.imu.extra == {"rate_hz": 400}


@pytest.mark.parametrize("old,new,key,near", [
    ("  feet_fixed_within: session", "  feet_fixed_whithin: station", "stance.feet_fixed_whithin", "feet_fixed_within"),
    ("  type: level", "  tpye: stairs", "ground.tpye", "type"),
])
def test_a_misspelt_ground_or_stance_key_is_refused_with_the_nearest_known_key(dataset_copy, old, new, key, near):
    """Kept and ignored, the misspelt key would leave the default it meant to change in force."""
    yaml_replace(f"\n{old}\n", f"\n{new}\n")(dataset_copy)
    with pytest.raises(DatasetError) as exc:
        read_dataset(dataset_copy)
    text = str(exc.value)
    assert "dataset.yaml" in text and key in text and f"did you mean '{near}'?" in text


def test_an_unknown_ground_key_no_known_key_resembles_is_kept(dataset_copy):
    yaml_replace("  type: level\n", "  type: level\n  surveyed_by: lidar\n")(dataset_copy)
    assert read_dataset(dataset_copy).ground == {"type": "level", "surveyed_by": "lidar"}


def test_yaml12_floats_and_defaults(dataset_copy):
    yaml_replace("sigma_mm: 50", "sigma_mm: 5e1")(dataset_copy)
    yaml_replace("ground:\n  type: level\nstance:\n  feet_fixed_within: session\n", "")(dataset_copy)
    ds = read_dataset(dataset_copy)
    assert ds.sensors["depth"].T_body_sensor_prior.sigma_m == 0.05
    assert ds.ground == {"type": "level"} and ds.stance == {"feet_fixed_within": "session"}


def test_lenient_csv_details(dataset_copy):
    """CRLF line ends, a UTF-8 BOM, spaces after commas, blank trailing lines are all accepted."""
    text = (dataset_copy / P).read_text()
    text = "\ufeff" + text.replace(",", ", ").replace("\n", "\r\n") + "\r\n\r\n"
    (dataset_copy / P).write_text(text, newline="")
    ds = read_dataset(dataset_copy)
    assert ds.planes.columns[0] == "station" and ds.planes["sensor"].tolist() == ["depth"] * 4
    assert ds.planes["d"].tolist() == [0.9, 0.91, 0.92, 0.93]


def test_number_with_a_non_ascii_space_is_read(dataset_copy):
    """A no-break space around a number (a spreadsheet export) is whitespace: the number is read.
    Found by the fuzz test: such a column used to end in an internal AssertionError. A Unicode digit
    is still refused with the file, row and column named."""
    set_cell(P, 2, "d", "\u00a00.91\u00a0")(dataset_copy)
    ds = read_dataset(dataset_copy)
    assert ds.planes["d"].tolist() == [0.9, 0.91, 0.92, 0.93]
    set_cell(P, 2, "d", "\u0660.91")(dataset_copy)  # ARABIC-INDIC DIGIT ZERO
    with pytest.raises(DatasetError, match=r"planes.csv.*row 2.*column d"):
        read_dataset(dataset_copy)


def test_warnings_of_a_valid_dataset(dataset_copy):
    drop_column(S, "session")(dataset_copy)
    set_cell(S, 2, "q_lf_tibia_joint", "143.2")(dataset_copy)  # degrees, by mistake
    yaml_replace("sensors:", "sensors:\n  laser:\n    type: laser_scanner\n    T_body_sensor_prior: "
                 "{xyz: [0.2, 0, 0.1], rpy_deg: [0, 0, 0], sigma_mm: 10, sigma_rpy_deg: 2}")(dataset_copy)
    report = validate_dataset(dataset_copy)
    assert report.warnings == (
        "stations.csv has no session column (which stations share a stance is unknown)",
        "sensor 'laser' has no cloud and no plane",
        "stations.csv: q_lf_tibia_joint outside the URDF limits [-2.5, 2.5] on 1 row(s)",
    )
    assert "warning: sensor 'laser' has no cloud and no plane" in report.summary()


def test_a_stations_file_without_rows_is_valid_but_warned_about(dataset_copy):
    """The contract allows an empty table, but calibrate refuses it: validate says so before."""
    for rel in (P, T, M, "clouds"):
        remove(rel)(dataset_copy)
    header_only(S)(dataset_copy)
    report = validate_dataset(dataset_copy)
    assert "stations.csv has a header but no rows: nothing to calibrate (calibrate refuses it)" in report.warnings


def test_a_depth_cloud_declared_laser_scanner_is_warned_about(dataset_copy):
    """A laser scanner's points are read as one scan line in its x-y plane: a depth camera's cloud
    declared ``laser_scanner`` (|z| up to metres) is named, with its file; a planar scan is not."""
    yaml_replace("type: depth_camera", "type: laser_scanner")(dataset_copy)
    report = validate_dataset(dataset_copy)
    (w,) = [w for w in report.warnings if "laser_scanner" in w]
    assert w.startswith("sensor 'depth' is a laser_scanner, but 1 of its 1 clouds do not lie in its scan plane z = 0")
    assert "clouds/depth/1.ply" in w and "type depth_camera" in w
    # the same file flattened onto z = 0 (a 2-D scan): no warning
    pts = read_ply(dataset_copy / "clouds/depth/1.ply")
    pts[:, 2] = np.random.default_rng(0).normal(0.0, 0.005, len(pts))  # 5 mm: inside the 20 mm bound
    write_ply(dataset_copy / "clouds/depth/1.ply", pts)
    assert not [w for w in validate_dataset(dataset_copy).warnings if "laser_scanner" in w]


def test_a_fractional_point_count_is_refused(dataset_copy):
    """planes.csv n_points counts points: 12.5 is refused with its row, line and column."""
    set_cell("planes.csv", 1, "n_points", "12.5")(dataset_copy)
    with pytest.raises(DatasetError, match=r"row 1 \(line 2\), column n_points.*whole number"):
        read_dataset(dataset_copy)
