"""The legged filter's noise settings: each value of :class:`~graphcal.locomotion.ekf.EkfNoise` with
where it came from (a file given with ``--noise``, dataset.yaml's ``tracker: noise:``, learned from
the log, or the real-robot default), read from and written to ``noise.yaml``
(``graphcal-track-noise/1``, SI units, each key's unit stated in the file). The defaults and their
reasons are in docs/state_estimation.md, "Noise settings"."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import yaml

from graphcal.errors import DatasetError
from graphcal.io.dataset.text import did_you_mean, shown_value
from graphcal.io.yaml_strict import StrictSafeLoader
from graphcal.locomotion.ekf import EkfNoise

__all__ = ["NOISE_FORMAT", "NOISE_UNITS", "REAL_ROBOT_NOISE", "NoiseSettings", "noise_values_from_file",
           "noise_values_from_dataset", "settings_from", "noise_document"]

NOISE_FORMAT = "graphcal-track-noise/1"

NOISE_UNITS = {
    "gyro_noise_density": "rad/s/sqrt(Hz)",
    "accel_noise_density": "m/s^2/sqrt(Hz)",
    "gyro_bias_rw": "rad/s^2/sqrt(Hz)",
    "accel_bias_rw": "m/s^3/sqrt(Hz)",
    "foot_rw": "m/sqrt(s)",
    "encoder_sigma_rad": "rad",
    "kinematic_sigma_m": "m",
    "icp_cov_scale": "1 (a factor on ICP's covariance)",
    "floor_sigma_m": "m",
}

#: what a real robot gets where neither the user nor the log gives a value: a MEMS IMU shaken by
#: its motors (gyro 1.6e-3, accel 5e-3 per sqrt(Hz): a Go1's order), biases that wander ten times
#: faster than the simulator's, planted feet that wander 0.1 mm per sqrt(s) (a slip is an event
#: for the plausibility check, not a diffusion), encoders read through gears
#: and backlash (2 mrad), and no extra kinematic noise until the innovations ask for it
#: (docs/state_estimation.md, "Noise settings"); the simulator's values are not these
REAL_ROBOT_NOISE = EkfNoise(gyro_noise_density=1.6e-3, accel_noise_density=5e-3, gyro_bias_rw=1e-4,
                            accel_bias_rw=1e-3, foot_rw=1e-4, encoder_sigma_rad=2e-3, kinematic_sigma_m=0.0,
                            icp_cov_scale=4.0, floor_sigma_m=0.01)


@dataclass(frozen=True)
class NoiseSettings:
    """The filter's noise and, per value (an EkfNoise field name), where it came from."""

    noise: EkfNoise
    sources: dict

    def given(self) -> frozenset:
        """The names not at their default: set by the user (a noise file, dataset.yaml, the caller) or learned."""
        return frozenset(k for k, s in self.sources.items() if not s.startswith("default"))

    def with_learned(self, values: dict, sources: dict) -> "NoiseSettings":
        """These values learned (name -> value, name -> where from); values not at their default are kept."""
        keep = {k: v for k, v in values.items() if k not in self.given()}
        return NoiseSettings(replace(self.noise, **keep), {**self.sources, **{k: sources[k] for k in keep}})


def _checked_values(m, path, where: str) -> dict:
    """A mapping of EkfNoise names -> finite numbers >= 0 (the unknown or misspelt name refused)."""
    names = [f.name for f in fields(EkfNoise)]
    if not isinstance(m, dict):
        raise DatasetError(path, where, "a mapping of noise names to numbers (SI units)", shown_value(m))
    out = {}
    for k, v in m.items():
        if k not in names:
            raise DatasetError(path, f"{where}.{k}", f"one of {', '.join(names)}{did_you_mean(str(k), names)}", k)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v >= 0 and v < float("inf")):
            raise DatasetError(path, f"{where}.{k}", f"a finite number >= 0 ({NOISE_UNITS[k]})", shown_value(v))
        out[k] = float(v)
    for k in ("icp_cov_scale", "floor_sigma_m"):
        if out.get(k, 1.0) <= 0:
            raise DatasetError(path, f"{where}.{k}", "a number > 0", out[k])
    return out


def noise_values_from_file(path: Path) -> dict:
    """The ``noise:`` values of a noise file (``graphcal-track-noise/1``: what ``graphcal track``
    writes as noise.yaml, or a hand-written subset); DatasetError naming the file and key."""
    path = Path(path)
    try:
        doc = yaml.load(path.read_text(encoding="utf-8"), Loader=StrictSafeLoader)  # noqa: S506 -- safe loader
    except OSError as exc:
        raise DatasetError(path, "file", "a readable noise file (YAML)", exc.strerror or str(exc)) from None
    except yaml.YAMLError as exc:
        raise DatasetError(path, "YAML syntax", "valid YAML", str(exc).splitlines()[0]) from None
    if not isinstance(doc, dict) or doc.get("format") != NOISE_FORMAT:
        raise DatasetError(path, "format", NOISE_FORMAT, doc.get("format") if isinstance(doc, dict) else doc)
    if "noise" not in doc:
        raise DatasetError(path, "noise", "a mapping of noise names to numbers (SI units)", "missing")
    return _checked_values(doc["noise"], path, "noise")


def noise_values_from_dataset(ds) -> dict:
    """dataset.yaml's ``tracker: noise:`` values ({} without a ``tracker`` block)."""
    block = ds.extra.get("tracker") if isinstance(ds.extra, dict) else None
    path = ds.root / "dataset.yaml" if ds.root is not None else "dataset.yaml"
    if block is None:
        return {}
    if not isinstance(block, dict) or set(block) - {"noise"}:
        raise DatasetError(path, "tracker", "a mapping with the key noise (docs/dataset.md)", shown_value(block))
    return _checked_values(block.get("noise") or {}, path, "tracker.noise")


def settings_from(dataset_values: dict, file_values: dict, *, file_name: str = "--noise",
                  base: EkfNoise = REAL_ROBOT_NOISE, base_source: str = "default (real robot)") -> NoiseSettings:
    """The real-robot defaults (or ``base``), dataset.yaml's values over them, a noise file's over both."""
    values = {f.name: getattr(base, f.name) for f in fields(EkfNoise)}
    sources = dict.fromkeys(values, base_source)
    for given, source in ((dataset_values, "dataset.yaml tracker.noise"), (file_values, file_name)):
        values.update(given)
        sources.update(dict.fromkeys(given, source))
    return NoiseSettings(EkfNoise(**values), sources)


def noise_document(settings: NoiseSettings, learning: dict | None = None) -> dict:
    """noise.yaml's document: the values (SI), their units, where each came from, how they were learned."""
    doc = {
        "format": NOISE_FORMAT,
        "note": "the legged filter's noise as graphcal track used it; give this file back with --noise to "
                "use these values (every key given is used as it is, none is learned)",
        "units": dict(NOISE_UNITS),
        "noise": {f.name: float(getattr(settings.noise, f.name)) for f in fields(EkfNoise)},
        "sources": dict(settings.sources),
    }
    if learning:
        doc["learning"] = learning
    return doc
