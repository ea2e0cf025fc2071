"""``graphcal simulate``: configuration from command-line words, simulation, and the dataset folder
(contract files + ``truth.yaml``) written atomically (:mod:`graphcal.simulation.write`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from graphcal.commands.result import folder_files
from graphcal.errors import GraphcalError
from graphcal.models.effects import CAUSES
from graphcal.simulation.effects import Effects, ExtrinsicChange, draw_effect, merge
from graphcal.simulation.session import SimulationConfig, leg_link_joints, simulate
from graphcal.simulation.write import SIMULATION_FILES, clouds_written, write_simulation

__all__ = ["run", "SimulateResult", "effect_from_words", "check_simulation_overwrite", "MOCAP_PROGRAM"]

_PARAMS = {
    "sensor_range_scale": {"sensor", "scale"},
    "session_offset": {"session", "offset_m"},
    "ground_tilt": {"tilt_rad", "axis_rad"},
    "imu_misalignment": {"angle_rad", "axis_rad"},
    "joint_offset": {"joint", "offset_rad"},
    "link_length": {"joint", "delta_m"},
    "extrinsic_change": {"sensor", "station", "angle_rad", "translation_m"},
    "outlier_stations": {"stations"},
    "foot_radius": {"radius_m"},
    "joint_compliance": {"joint_index", "k_rad_per_m"},
}


def _number(cause: str, key: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise GraphcalError(f"--effect {cause}: {key}={text!r} is not a number (SI units)") from None
    if not np.isfinite(value):
        raise GraphcalError(f"--effect {cause}: {key} must be finite")
    return value


def effect_from_words(cause: str, params: dict, *, seed: int, config: SimulationConfig) -> Effects:
    """One ``--effect`` argument -> :class:`Effects`. Without parameters the magnitude and location
    are drawn from ``seed`` (see :func:`draw_effect`)."""
    if cause not in CAUSES:
        raise GraphcalError(f"--effect: unknown cause {cause!r}; expected one of {', '.join(CAUSES)}")
    unknown = set(params) - _PARAMS[cause]
    if unknown:
        raise GraphcalError(
            f"--effect {cause}: unknown parameter(s) {', '.join(sorted(unknown))}; "
            f"expected {', '.join(sorted(_PARAMS[cause]))}"
        )
    if not params:
        from graphcal.simulation.programs import station_program
        from graphcal.simulation.session import robot_and_info

        robot, info = robot_and_info(config)
        cmds = station_program(config.program, default_height_m=info.default_body_height_m,
                               n_stations=config.n_stations, n_sessions=config.n_sessions, seed=config.seed)
        sensors = tuple(config.sensors) if config.sensors else tuple(info.sensors)
        if cause in ("sensor_range_scale", "extrinsic_change") and not sensors:
            raise GraphcalError(f"--effect {cause}: robot {config.robot!r} has no exteroceptive sensor")
        eff, _ = draw_effect(
            cause,
            np.random.default_rng([seed, CAUSES.index(cause)]),
            sensors=sensors,
            sessions=tuple(dict.fromkeys(c.session for c in cmds)),
            stations=tuple(c.station for c in cmds),
            leg_joints={f: robot.leg(f).joint_names for f in robot.feet},
            link_joints=leg_link_joints(robot),
        )
        return eff

    def need(key):
        if key not in params:
            raise GraphcalError(f"--effect {cause}: missing parameter {key}")
        return params[key]

    num = lambda key: _number(cause, key, need(key))  # noqa: E731
    if cause == "sensor_range_scale":
        return Effects(sensor_range_scale={need("sensor"): num("scale")})
    if cause == "session_offset":
        return Effects(session_offset={need("session"): num("offset_m")})
    if cause == "ground_tilt":
        return Effects(ground_tilt=(num("tilt_rad"), _number(cause, "axis_rad", params.get("axis_rad", "0"))))
    if cause == "imu_misalignment":
        return Effects(imu_misalignment=(num("angle_rad"), _number(cause, "axis_rad", params.get("axis_rad", "0"))))
    if cause == "joint_offset":
        return Effects(joint_offset={need("joint"): num("offset_rad")})
    if cause == "link_length":
        return Effects(link_length={need("joint"): num("delta_m")})
    if cause == "extrinsic_change":
        rng = np.random.default_rng(seed)
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        shift = _number(cause, "translation_m", params.get("translation_m", "0"))
        return Effects(extrinsic_change=ExtrinsicChange(
            need("sensor"), int(num("station")), num("angle_rad"), tuple(axis), tuple(shift * axis)))
    if cause == "foot_radius":
        return Effects(foot_radius=num("radius_m"))
    if cause == "joint_compliance":
        return Effects(joint_compliance=(int(num("joint_index")), num("k_rad_per_m")))
    stations = tuple(int(_number(cause, "stations", s)) for s in need("stations").split(";") if s.strip())
    return Effects(outlier_stations=stations)


@dataclass(frozen=True)
class SimulateResult:
    """What ``graphcal simulate`` wrote.

    Attributes:
        out: the dataset folder (with ``truth.yaml``, the hidden truth).
        robot, program: as given (``program``: a station program, ``mocap`` or a walk).
        simulation: the simulator's result (:class:`~graphcal.simulation.session.SimulationResult`,
            :class:`~graphcal.simulation.mocap.MocapSimulation`; None for a walk, written by
            :func:`graphcal.simulation.write.simulate_walking_to_folder`).
        files: the dataset folder's entries.
        warnings, verdict: none (empty, None).
        ground: the ground (station programs).
        n_stations: stations (station programs) or motion-capture samples (mocap).
        n_sessions, sensors, n_clouds, n_planes, hidden_effects: station programs: sessions,
            simulated sensors, clouds and planes written, the causes hidden.
        foot, leg_errors: mocap: the leg's foot, and where its true errors come from.
        walk_summary: a walk: the walking simulator's own summary.
    """

    out: Path
    robot: str
    program: str
    simulation: object
    files: tuple[Path, ...]
    warnings: tuple[str, ...] = ()
    verdict: str | None = None
    ground: str = "level"
    n_stations: int = 0
    n_sessions: int = 0
    sensors: tuple[str, ...] = ()
    n_clouds: int = 0
    n_planes: int = 0
    hidden_effects: tuple[str, ...] = ()
    foot: str = ""
    leg_errors: str = ""
    walk_summary: str = ""

    @property
    def truth(self) -> Path:
        """The hidden truth (``truth.yaml`` beside ``dataset.yaml``)."""
        return self.out / "truth.yaml"

    def summary_text(self) -> str:
        if self.walk_summary:
            return self.walk_summary
        if self.program == MOCAP_PROGRAM:
            return (f"wrote {self.out}: {self.n_stations} motion-capture samples of the {self.robot}'s {self.foot} leg "
                    f"in the air ({MOCAP_PROGRAM} program, Yuan et al.'s set-up: +-1 deg encoder and +-1 mm marker "
                    f"noise, body markers); leg errors: {self.leg_errors}; truth in {self.truth}; identify with: "
                    f"graphcal identify-legs {self.out} --out DIR --mocap-free rz,z --origins none (Yuan et al.'s "
                    "unknowns: the defaults also free the hip's origin and the frame's roll, which then share the "
                    "planted hip offset; docs/legs.md)")
        return (f"wrote {self.out}: {self.n_stations} stations in {self.n_sessions} session(s) of the {self.robot} "
                f"({self.program} program, {self.ground} ground); sensors: {', '.join(self.sensors) or 'none'}; "
                f"{self.n_clouds} clouds, {self.n_planes} planes; hidden effects: "
                f"{', '.join(self.hidden_effects) or 'none'}; truth in {self.truth}")


def run(
    *,
    robot: str | None,
    program: str,
    ground: str,
    out_dir: str | Path,
    seed: int = 0,
    n_stations: int | None = None,
    n_sessions: int = 1,
    sensors: tuple[str, ...] | None = None,
    output: str = "both",
    cloud_stride: int | None = 4,
    leg_errors: bool = False,
    effects: Sequence[tuple[str, dict]] = (),
    overwrite: bool = False,
    progress: bool = True,
    session_heading_step_deg: float = 8.0,
    distance_m: float | None = None,
    duration_s: float | None = None,
    cloud_rate_hz: float | None = None,
    real_like: bool = False,
    walk: dict | None = None,
) -> SimulateResult:
    """Simulate and write the dataset folder ``out_dir`` (contract files and ``truth.yaml``).

    Args:
        output: ``clouds`` (PLY per station), ``planes`` (planes.csv only) or ``both``.
        effects: (cause, parameters as text) pairs, e.g. ``("link_length", {"joint": "rm_foot_joint",
            "delta_m": "0.015"})``; no parameters: drawn from the seed.
        leg_errors: random joint-offset (0.5 deg) and link-length (3 mm) errors on every leg joint.
        cloud_stride: None = 4 (walking programs: 16 level, 8 stairs).
        real_like: a walking program written as a real robot's log (raw foot counts, stand-up and
            lie-down, IMU off the base, other noise: :mod:`graphcal.simulation.real_like`).
        distance_m, duration_s, cloud_rate_hz: the walking programs (``tripod-walk``,
            ``tripod-stairs`` of the qingzhui, ``trot``, ``walk`` of the a1:
            :mod:`graphcal.simulation.walking`) only.
        walk: the walking programs: more :class:`~graphcal.simulation.walking.WalkingConfig` fields
            (``cad_error_m``, ``cad_error_rad``, ``camera_delay_s``, ``sway_rad``, ``nod_rad``; SI units).
    Returns:
        A :class:`SimulateResult` (its summary: one paragraph on what was written).
    """
    from graphcal.simulation.walking import GAITS, WALKING_PROGRAMS

    if robot is None:  # the walking program's own robot, otherwise the Octopus
        robot = GAITS[program].robot if program in GAITS else "octopus"
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise GraphcalError(f"--seed must be a whole number >= 0, got {seed}")
    if n_stations is not None and program not in ("random", MOCAP_PROGRAM):
        raise GraphcalError(f"--stations applies to the random and mocap programs; {program} has its own "
                            f"stations (leave --stations out)")
    if n_stations is not None and n_stations < 1:
        raise GraphcalError(f"--stations must be >= 1, got {n_stations}")
    if overwrite:
        check_simulation_overwrite(Path(out_dir))
    if not Path(out_dir).exists():
        from graphcal.io.atomic import check_output_location

        check_output_location(out_dir)  # before the work
    if program == MOCAP_PROGRAM:
        return _mocap_to_folder(robot=robot, out_dir=out_dir, seed=seed, n_stations=n_stations, leg_errors=leg_errors,
                                overwrite=overwrite, unsupported=(
                                    ("--ground", ground != "level"), ("--effect", bool(effects)),
                                    ("--sessions", n_sessions != 1), ("--sensor", bool(sensors)),
                                    ("--output", output != "both"), ("--cloud-stride", cloud_stride not in (None, 4)),
                                    ("--distance", distance_m is not None), ("--duration", duration_s is not None),
                                    ("--cloud-rate", cloud_rate_hz is not None), ("--cad-error/--camera-delay/--sway",
                                                                                  bool(walk))))
    if program in WALKING_PROGRAMS:
        return _walk_to_folder(program=program, robot=robot, out_dir=out_dir, seed=seed, output=output,
                               cloud_stride=cloud_stride, leg_errors=leg_errors, effects=effects,
                               n_stations=n_stations, n_sessions=n_sessions, sensors=sensors,
                               overwrite=overwrite, progress=progress, distance_m=distance_m,
                               duration_s=duration_s, cloud_rate_hz=cloud_rate_hz, real_like=real_like,
                               walk=walk)
    if walk:
        raise GraphcalError("--cad-error-mm, --cad-error-deg, --camera-delay-ms and --sway-deg belong to the walking "
                            "programs (tripod-walk, tripod-stairs, trot, walk)")
    if real_like:
        raise GraphcalError("--real-like belongs to the walking programs (tripod-walk, trot, walk)")
    if distance_m is not None or duration_s is not None or cloud_rate_hz is not None:
        raise GraphcalError("--distance, --duration and --cloud-rate belong to the walking programs "
                            "(tripod-walk, tripod-stairs, trot, walk)")
    if cloud_stride is None:
        cloud_stride = 4
    if output not in ("clouds", "planes", "both"):
        raise GraphcalError(f"output must be clouds, planes or both, got {output!r}")
    if cloud_stride < 1:
        raise GraphcalError(f"--cloud-stride must be >= 1, got {cloud_stride}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise GraphcalError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise GraphcalError(f"{out_dir}: folder exists and is not empty; choose another --out or pass --overwrite")
    config = SimulationConfig(
        robot=robot, program=program, ground=ground, seed=seed, n_stations=n_stations, n_sessions=n_sessions,
        sensors=sensors, cloud_stride=cloud_stride,
        leg_error_sigma_rad=float(np.radians(0.5)) if leg_errors else 0.0,
        leg_error_sigma_m=0.003 if leg_errors else 0.0,
        session_heading_step_deg=session_heading_step_deg,
    )
    _refuse_without_sensors(config)
    combined = Effects()
    for cause, params in effects:
        combined = merge(combined, effect_from_words(cause, params, seed=seed, config=config))
    from dataclasses import replace

    config = replace(config, effects=combined)
    result = simulate(config, progress=progress)
    ds = write_simulation(result, out_dir, output=output, overwrite=overwrite, progress=progress)
    return SimulateResult(out=out_dir, robot=robot, program=program, simulation=result, files=folder_files(out_dir),
                          ground=ground, n_stations=len(result.stations),
                          n_sessions=len(set(r.session for r in result.stations)), sensors=tuple(result.sensor_cad),
                          n_clouds=len(clouds_written(result, output)),
                          n_planes=len(ds.planes) if ds.planes is not None else 0,
                          hidden_effects=tuple(combined.active()))


def _refuse_without_sensors(config: SimulationConfig) -> None:
    """A station program simulates what the robot's sensors see of the ground; a robot without an
    exteroceptive sensor (the a1) gave a dataset that validate called valid and calibrate refused."""
    from graphcal.models.builtin import builtin_info

    if config.custom_robot is not None or config.sensors:
        return
    if not builtin_info(config.robot).sensors:
        raise GraphcalError(f"--robot {config.robot} has no exteroceptive sensor (camera or laser), so the station "
                            f"program {config.program} has nothing to calibrate; for the {config.robot} use "
                            f"--program {MOCAP_PROGRAM} (a leg in a motion-capture room, for identify-legs)")


def check_simulation_overwrite(out_dir: Path) -> None:
    """OutputExistsError unless ``out_dir`` is absent, empty, or a previous simulation: its
    ``truth.yaml`` says ``graphcal-truth/`` and it holds nothing but :data:`SIMULATION_FILES`.
    ``--overwrite`` replaces a simulation, never a folder of the user's (a measured dataset has no
    truth.yaml)."""
    from graphcal.io.atomic import OutputExistsError, previous_output_files

    if out_dir.is_symlink() or (out_dir.exists() and not out_dir.is_dir()):
        raise OutputExistsError(f"{out_dir}: exists and is not a folder; --overwrite replaces only a previous simulation")
    if not out_dir.is_dir() or not any(out_dir.iterdir()):
        return
    ours = previous_output_files(out_dir, "truth.yaml", SIMULATION_FILES, "graphcal-truth/")
    if ours is None:
        raise OutputExistsError(f"{out_dir}: not a previous graphcal simulation (no graphcal truth.yaml); "
                                f"--overwrite replaces only those: choose another --out")
    other = sorted(p.name for p in out_dir.iterdir() if p.name not in SIMULATION_FILES)
    if other:
        raise OutputExistsError(f"{out_dir}: holds files a simulation did not write ({', '.join(other[:5])}); "
                                f"--overwrite replaces only a previous simulation: move them or choose another --out")


#: the motion-capture program (Yuan et al.): a leg in the air, its foot marker and the body markers
MOCAP_PROGRAM = "mocap"
#: samples of the motion-capture program when --stations is not given (Yuan's Table I: 1000)
MOCAP_DEFAULT_SAMPLES = 1000


def _mocap_to_folder(*, robot, out_dir, seed, n_stations, leg_errors, overwrite, unsupported) -> SimulateResult:
    """The motion-capture program: Yuan et al.'s Table I session (:func:`.mocap.simulate_yuan_session`)
    on the A1; on another robot the same session of its first leg. The leg's true errors: Table I's
    (A1), none (other robots), or with ``leg_errors`` drawn from the seed (0.5 deg, 3 mm)."""
    from graphcal.models.perturb import LegPerturbation, link_length_delta
    from graphcal.models.robot import load_robot
    from graphcal.simulation.mocap import YUAN_FOOT, YUAN_PERTURBATION, simulate_mocap, simulate_yuan_session, write_mocap_simulation
    from graphcal.simulation.session import draw_leg_errors

    refused = [name for name, given in unsupported if given]
    if refused:
        raise GraphcalError(f"program {MOCAP_PROGRAM}: {', '.join(refused)} not supported (a leg in the air "
                            f"in the motion-capture room: --robot, --stations, --seed, --leg-errors)")
    n = MOCAP_DEFAULT_SAMPLES if n_stations is None else int(n_stations)  # >= 1: run
    model = load_robot(model=robot)
    foot = YUAN_FOOT if robot == "a1" else model.feet[0]
    if leg_errors:
        offsets, lengths = draw_leg_errors(model, (foot,), float(np.radians(0.5)), 0.003, np.random.default_rng(seed))
        perturbation = LegPerturbation(offsets, {j: tuple(float(x) for x in link_length_delta(model, j, d))
                                                 for j, d in lengths.items()})
        errors = "drawn from the seed (0.5 deg, 3 mm)"
    elif robot == "a1":
        perturbation, errors = YUAN_PERTURBATION, "Yuan et al.'s Table I"
    else:
        perturbation, errors = LegPerturbation(), "none (pass --leg-errors to draw some)"
    if robot == "a1":
        sim = simulate_yuan_session(n, seed, perturbation=perturbation)
    else:
        sim = simulate_mocap(robot, feet=(foot,), base_frame=model.base_frame, n_samples=n,
                             perturbation=perturbation, joint_noise_rad=float(np.radians(1.0)), marker_noise_m=0.001,
                             noise="uniform", body_markers=True, body_marker_noise_m=0.0, seed=seed)
    out = Path(write_mocap_simulation(sim, out_dir, overwrite=overwrite))
    return SimulateResult(out=out, robot=robot, program=MOCAP_PROGRAM, simulation=sim, files=folder_files(out),
                          n_stations=n, foot=foot, leg_errors=errors)


def _walk_to_folder(*, program, robot, out_dir, seed, output, cloud_stride, leg_errors, effects, n_stations,
                    n_sessions, sensors, overwrite, progress, distance_m, duration_s, cloud_rate_hz,
                    real_like=False, walk=None) -> SimulateResult:
    """The walking programs: refuse the station-program options, then simulate the walk."""
    from graphcal.simulation.write import simulate_walking_to_folder

    unsupported = [name for name, given in (
        ("--effect", bool(effects)), ("--leg-errors", leg_errors), ("--stations", n_stations is not None),
        ("--sessions", n_sessions != 1), ("--sensor", bool(sensors)), ("--output planes", output == "planes"),
    ) if given]
    if unsupported:
        raise GraphcalError(f"program {program}: {', '.join(unsupported)} not supported by the walking programs")
    from graphcal.simulation.walking import GAITS

    if robot != GAITS[program].robot:
        what = "Zhao 2020's tripod gait" if GAITS[program].phase_offsets is None else f"a quadruped {program}"
        raise GraphcalError(f"program {program} walks the {GAITS[program].robot} ({what}), not {robot!r}: "
                            f"pass --robot {GAITS[program].robot}")
    text = simulate_walking_to_folder(program=program, out_dir=out_dir, robot=robot, seed=seed,
                                      distance_m=distance_m, duration_s=duration_s, cloud_rate_hz=cloud_rate_hz,
                                      cloud_stride=cloud_stride, overwrite=overwrite, progress=progress,
                                      real_like=real_like, walk=walk)
    return SimulateResult(out=Path(out_dir), robot=robot, program=program, simulation=None,
                          files=folder_files(out_dir), walk_summary=text)
