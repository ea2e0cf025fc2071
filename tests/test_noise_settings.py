"""The legged filter's noise settings (issue 42 item 1): noise.yaml read back, dataset.yaml's
``tracker: noise:``, precedence, refusals naming the file and key; the still-window learner."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import DatasetError
from graphcal.locomotion.noise_settings import (
    NOISE_FORMAT,
    REAL_ROBOT_NOISE,
    noise_document,
    noise_values_from_file,
    settings_from,
)


def test_a_written_noise_file_reads_back_and_wins_over_dataset_yaml(tmp_path):
    import yaml

    s = settings_from({"encoder_sigma_rad": 0.003, "foot_rw": 2e-4}, {})
    assert s.noise.encoder_sigma_rad == 0.003 and s.sources["encoder_sigma_rad"] == "dataset.yaml tracker.noise"
    assert s.noise.gyro_noise_density == REAL_ROBOT_NOISE.gyro_noise_density
    assert s.sources["gyro_noise_density"] == "default (real robot)"
    f = tmp_path / "noise.yaml"
    f.write_text(yaml.safe_dump(noise_document(s)))
    values = noise_values_from_file(f)
    assert values["encoder_sigma_rad"] == 0.003 and set(values) == set(noise_document(s)["noise"])
    both = settings_from({"encoder_sigma_rad": 0.003}, {"encoder_sigma_rad": 0.001}, file_name="--noise f")
    assert both.noise.encoder_sigma_rad == 0.001 and both.sources["encoder_sigma_rad"] == "--noise f"
    assert both.given() == {"encoder_sigma_rad"}


@pytest.mark.parametrize("body, where, words", [
    ("noise: {encoder_sigma: 0.001}", "noise.encoder_sigma", "did you mean 'encoder_sigma_rad'"),
    ("noise: {foot_rw: -1}", "noise.foot_rw", "a finite number >= 0"),
    ("noise: {foot_rw: .inf}", "noise.foot_rw", "a finite number >= 0"),
    ("noise: {floor_sigma_m: 0}", "noise.floor_sigma_m", "a number > 0"),
    ("noise: {foot_rw: true}", "noise.foot_rw", "a finite number >= 0"),
    ("noise: [1, 2]", "noise", "a mapping of noise names"),
])
def test_a_bad_noise_file_is_refused_naming_the_key(tmp_path, body, where, words):
    f = tmp_path / "n.yaml"
    f.write_text(f"format: {NOISE_FORMAT}\n{body}\n")
    with pytest.raises(DatasetError) as e:
        noise_values_from_file(f)
    assert e.value.where == where and words in str(e.value) and str(f) in str(e.value)


def test_a_noise_file_of_another_format_is_refused(tmp_path):
    f = tmp_path / "n.yaml"
    f.write_text("format: graphcal-calibration/1\nnoise: {}\n")
    with pytest.raises(DatasetError, match="format: expected graphcal-track-noise/1"):
        noise_values_from_file(f)


def test_still_noise_reads_white_noise_and_ignores_motion():
    """Two still seconds and one of motion at 400 Hz: the sigmas of the still part within 5 %; a
    quantised, constant encoder counts as white (its quantum / sqrt(12))."""
    from graphcal.locomotion.noise_learning import still_noise

    rng = np.random.default_rng(0)
    t = np.arange(0, 3.0, 0.0025)
    moving = (t > 1.0) & (t < 2.0)
    q = np.column_stack([0.3 + 1e-3 * rng.standard_normal(len(t)) + np.where(moving, 0.5 * np.sin(3 * t), 0.0),
                         np.round(np.full(len(t), 0.7) / 1e-4) * 1e-4])
    q[np.arange(len(t)) % 7 == 0, 1] += 1e-4  # the constant encoder shows its quantum now and then
    gyro = 2e-3 * rng.standard_normal((len(t), 3)) + np.where(moving, 0.4, 0.0)[:, None] * np.sin(5 * t)[:, None]
    accel = np.array([0, 0, 9.81]) + 0.02 * rng.standard_normal((len(t), 3))
    sn = still_noise(t, q, gyro, accel)
    assert sn is not None and 1.7 <= sn.duration_s <= 2.0
    assert all(not (1.05 < a < 1.95) for a, _ in sn.windows)  # no window starts inside the motion
    assert sn.gyro_sigma == pytest.approx(2e-3, rel=0.05) and sn.accel_sigma == pytest.approx(0.02, rel=0.05)
    assert sn.gyro_noise_density == pytest.approx(2e-3 * np.sqrt(0.0025), rel=0.05)
