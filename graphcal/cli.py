"""graphcal command line. Only argument parsing and wiring live here; every command calls its
``graphcal.commands.<name>.run`` and prints the ``summary_text()`` of the result it returns
(stdout; :mod:`graphcal.commands.result`). Messages go through
``logging`` to stderr (``--quiet``: warnings only; ``--verbose``: debug), progress bars through tqdm.
graphcal's own errors (bad input) print one line and exit with code 2; anything else is a
bug and keeps its traceback."""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import sys
from pathlib import Path


def _effect_arg(text: str):
    """``cause`` or ``cause:key=value,key=value`` (SI units) -> (cause, dict)."""
    cause, _, rest = text.partition(":")
    params = {}
    if rest:
        for item in rest.split(","):
            key, eq, val = item.partition("=")
            if not eq:
                raise argparse.ArgumentTypeError(f"--effect {text!r}: expected key=value after ':'")
            params[key.strip()] = val.strip()
    return cause.strip(), params


class _DefaultsHelpFormatter(argparse.HelpFormatter):
    """Shows ``(default: X)`` after an option's help when it has a default worth showing (not None,
    False or empty) and its help does not already say it."""

    def _get_help_string(self, action) -> str:
        text = action.help or ""
        shown = not (action.default is None or action.default is False or action.default == []
                     or action.default == argparse.SUPPRESS)
        if action.option_strings and shown and "(default" not in text:
            text += " (default: %(default)s)"
        return text


def _add_import_parser(sub, common) -> None:
    """``graphcal import LOG --out DATASET`` (docs/import.md)."""
    im = sub.add_parser("import", help="a robot log (ROS 1/2 bag, MCAP, CSV) -> dataset: stations found in still "
                                       "windows, import_map.yaml and import_report.yaml (docs/import.md)",
                        parents=[common])
    im.add_argument("log", type=Path, help="a .bag file, a ROS 2 bag folder, a .mcap file or a .csv file")
    im.add_argument("--out", required=True, type=Path, help="dataset folder to write (must not exist or be empty)")
    im.add_argument("--map", type=Path, default=None, help="import map (the import_map.yaml of an earlier import, "
                    "edited; for a CSV log its column map)")
    im.add_argument("--urdf", type=Path, default=None, help="the robot's URDF (instead of /robot_description or the map's "
                    "robot.urdf, which may then be left out)")
    im.add_argument("--receive-time", action="store_true", help="time messages by receive time, not header stamps")
    im.add_argument("--msg-dir", type=Path, default=None,
                    help="folder of .msg definitions (<pkg>/msg/<Name>.msg) for message types rosbags does not know")
    im.add_argument("--timeseries", action="store_true",
                    help="also write timeseries.csv (every joint sample, for track; memory grows with the log) and, "
                         "from a bag, the depth images / PointCloud2 messages along the walk as clouds")
    im.add_argument("--cloud-rate", type=float, default=None, metavar="HZ",
                    help="with --timeseries: thin the clouds along the walk to this rate (Hz; default 5, 0 = none)")
    im.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")


def _add_plan_gait_parser(sub, common) -> None:
    """``graphcal plan-gait TRACK_DIR --out DIR`` (docs/stairs_gait.md)."""
    pg = sub.add_parser("plan-gait", help="Zhao's gait adaptation up the stairs a track perceived: per step the step "
                                          "length and height, body height and pitch, the swinging tripod, footholds "
                                          "with their edge distances and clearances (gait.yaml, report.html)",
                        parents=[common], formatter_class=_DefaultsHelpFormatter)
    pg.add_argument("track_dir", type=Path, metavar="TRACK_DIR",
                    help="a graphcal track output of a stairs dataset (stairs.json, trajectory.tum, metrics.json)")
    pg.add_argument("--out", required=True, type=Path,
                    help="output folder (replaces only an empty folder or a previous plan-gait output)")
    pg.add_argument("--dataset", type=Path, default=None,
                    help="the dataset the track ran on (robot model, joint angles); default: the one metrics.json names")
    pg.add_argument("--start-time", type=float, default=None, metavar="S",
                    help="start the plan at the tracked sample nearest this time (s); default: the last moment "
                         "before the stairs with every foot down")
    pg.add_argument("--max-steps", type=int, default=40, metavar="N", help="most steps planned")
    pg.add_argument("--min-tread-points", type=int, default=150, metavar="N",
                    help="a tread of stairs.json with fewer points is refused (not stepped on)")


class _CommandParser(argparse.ArgumentParser):
    """A command's parser: its errors also name the flags it has closest to a misspelt one in the
    command line (``--ouput`` -> ``--out``), whatever argparse complains about first."""

    argv: list[str] = []

    def error(self, message: str):
        import difflib
        import re

        flags = sorted(set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", self.format_help())))
        hints = []
        for a in self.argv:
            name = a.split("=")[0]
            if name.startswith("--") and name not in flags and "did you mean" not in message:
                close = difflib.get_close_matches(name, flags, n=3, cutoff=0.6)
                hints.append(f"{name}: did you mean {', '.join(close)}?" if close else f"{name}: no such flag")
        super().error(message + (f" ({'; '.join(hints)})" if hints else ""))


def _add_track_parser(sub, common, dataset_help: str) -> None:
    """``graphcal track`` (docs/state_estimation.md)."""
    tr = sub.add_parser("track", help="estimate the body trajectory of a timeseries dataset (EKF: IMU, leg "
                                      "kinematics, ICP): trajectory.tum, metrics.json, plots, report", parents=[common])
    tr.add_argument("dataset", type=Path, help=dataset_help)
    tr.add_argument("--out", required=True, type=Path,
                    help="output folder (replaces only an empty folder or a previous track output)")
    tr.add_argument("--tum-rate", type=float, default=100.0,
                    help="poses per second in trajectory.tum (default 100; 0 = every sample)")
    tr.add_argument("--no-icp", action="store_true", help="proprioception only (no ICP between clouds)")
    tr.add_argument("--noise", type=Path, default=None, metavar="FILE",
                    help="the filter's noise (noise.yaml's format, SI units: a track output's noise.yaml, or a subset "
                         "of its keys); every value given is used as it is")
    tr.add_argument("--no-noise-learning", action="store_true",
                    help="do not learn the noise nobody gave from the log (still windows, stance innovations): use "
                         "the real-robot defaults (docs/state_estimation.md, 'Noise settings')")


def _build_parser() -> argparse.ArgumentParser:
    from graphcal import __version__

    p = argparse.ArgumentParser(
        prog="graphcal",
        description="Self-calibration and state estimation for legged robots (factor graphs).",
    )
    p.add_argument("--version", action="version", version=f"graphcal {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_CommandParser)
    p.set_defaults(subcommands=sub.choices)  # name -> its parser, for the unknown-flag message
    # every command: --quiet / --verbose (log levels, configure_logging); DATASET (the positional)
    common = _CommandParser(add_help=False)
    talk = common.add_mutually_exclusive_group()
    talk.add_argument("--quiet", action="store_true",
                      help="no progress bars, only warnings and errors on stderr (the summary still goes to stdout)")
    talk.add_argument("--verbose", action="store_true", help="also debug messages on stderr")
    dataset_help = "dataset folder (dataset.yaml and its files; the contract: docs/dataset.md)"

    _add_simulate_parser(sub, common)

    v = sub.add_parser("validate", help="check a dataset against the contract (docs/dataset.md)", parents=[common])
    v.add_argument("dataset", type=Path, help=dataset_help)

    c = sub.add_parser("calibrate", help="calibrate the sensors (and legs) of a dataset: calibration.yaml, URDF, report", parents=[common])
    c.add_argument("dataset", type=Path, help=dataset_help)
    c.add_argument("--out", required=True, type=Path,
                   help="output folder (created; a previous graphcal calibration there is replaced only at the end)")
    c.add_argument("--incremental", action="store_true", help="iSAM2, one station at a time, with change detection")
    c.add_argument("--legs", action="store_true", help="also estimate leg joint offsets and link lengths")
    c.add_argument("--ground-roughness-mm", type=float, default=0.0, metavar="MM",
                   help="RMS height of bumps in the ground (default 0: a flat floor). On uneven ground the "
                        "feet stand on bumps and within one stance that cannot be told from the extrinsic; "
                        "this puts it into the sigma (docs/calibration.md)")
    c.add_argument("--time-offset-ms", action="append", default=[], metavar="SENSOR=MS",
                   help="a walking dataset: the camera's known time offset (its stamp minus its capture time, ms); "
                        "not estimated then (repeatable; default: every camera's is estimated from the walk)")
    c.add_argument("--plane-points", type=int, default=None, metavar="N",
                   help="fit each cloud's ground plane on at most N of its points, every k-th one (default: "
                        "all). Faster on large clouds, a little less accurate: on 258k-point Kinect clouds 50000 "
                        "took 0.5-0.6x the time, with 35 %% more translation error (docs/calibration.md). No effect "
                        "when the dataset has planes.csv")
    c.add_argument("--scene-max-points", type=int, default=20_000, metavar="N",
                   help="each station's cloud in scene.mcap evenly thinned to at most N points (default 20000; "
                        "0: every point; docs/outputs.md)")
    c.add_argument("--noise-from", type=Path, default=None, metavar="CALIBRATION_YAML",
                   help="use the noise model (noise_model) of an earlier calibration.yaml of this robot as "
                        "given instead of learning it; for --incremental, which cannot learn it "
                        "(docs/incremental.md)")

    g = sub.add_parser("suggest-poses", help="propose the k body poses that most shrink the extrinsic covariance", parents=[common])
    g.add_argument("dataset", type=Path, help=dataset_help)
    g.add_argument("-k", type=int, default=10, help="number of poses (default 10; with targets, the most)")
    g.add_argument("--sigma-target-deg", type=float, nargs="+", default=None, metavar="DEG",
                   help="aim at this 1-sigma of the extrinsic's rotation (one value, or three: body x y z) and "
                        "stop as soon as it and --sigma-target-mm are reached")
    g.add_argument("--sigma-target-mm", type=float, nargs="+", default=None, metavar="MM",
                   help="the same for the translation (mm)")
    g.add_argument("--out", type=Path, default=None, help="write the poses as CSV here")
    g.add_argument("--after-existing", action="store_true",
                   help="count the dataset's own stations (its first session) as done: suggest the k to add")
    g.add_argument("--noise-from", type=Path, default=None, metavar="CALIBRATION_YAML",
                   help="predict sigma with the noise model an earlier calibration of this robot learned "
                        "(default: graphcal's defaults, which a calibration usually improves on)")

    e = sub.add_parser("extract-planes", help="fit planes to a dataset's clouds and write planes.csv", parents=[common])
    e.add_argument("dataset", type=Path, help=dataset_help)
    e.add_argument("--out", type=Path, default=None,
                   help="planes file to write (default: DATASET/planes.csv, or DATASET/planes-extracted.csv beside "
                        "the dataset's own planes.csv, which is kept)")
    e.add_argument("--overwrite", action="store_true",
                   help="replace --out (default: DATASET/planes.csv); the old file is kept as NAME.bak")
    e.add_argument("--max-planes", type=int, default=1, metavar="K",
                   help="planes to extract from each cloud, largest first (default 1: the ground; more for stairs)")
    e.add_argument("--plane-points", type=int, default=None, metavar="N",
                   help="fit each cloud's planes on at most N of its points, every k-th one (default: all); "
                        "as calibrate --plane-points")

    dg = sub.add_parser("diagnose", help="what the model gets wrong on these data: named causes, evidence, "
                                         "held-out gain (diagnosis.json, report.html)", parents=[common])
    dg.add_argument("dataset", type=Path, help=dataset_help)
    dg.add_argument("--out", required=True, type=Path,
                    help="output folder (new, empty, or a previous diagnosis, replaced only at the end)")

    il = sub.add_parser("identify-legs", help="identify leg kinematic parameters from motion capture (mocap.csv): "
                                              "legs.yaml, calibrated URDF, report", parents=[common])
    il.add_argument("dataset", type=Path, help=dataset_help)
    il.add_argument("--out", required=True, type=Path, help="output folder (replaces only a previous identify-legs output)")
    il.add_argument("--mocap-free", default=None,
                    help="unknown components of T_body_mocap, e.g. 'rz,z' (Yuan's alpha_h, z_h); default all six")
    il.add_argument("--origins", choices=("first", "all", "none"), default="first",
                    help="3-D joint origin changes: first joint only (hip position, default), every joint, none")
    il.add_argument("--sigma-marker-mm", type=float, default=None,
                    help="physical marker noise (mm); default: dataset.yaml mocap.sigma_mm, else 1")
    il.add_argument("--sigma-joint-deg", type=float, default=None,
                    help="physical joint encoder noise (deg); default: dataset.yaml mocap.sigma_joint_deg, else 0")
    il.add_argument("--robust", choices=("none", "huber", "cauchy"), default="none",
                    help="robust loss per posture sample (down-weights gross postures); default none")

    _add_track_parser(sub, common, dataset_help)
    _add_import_parser(sub, common)
    _add_plan_gait_parser(sub, common)
    _add_batch_parsers(sub, common)
    return p


def _add_batch_parsers(sub, common) -> None:
    """``graphcal batch`` and ``graphcal study`` (docs/batch.md)."""
    b = sub.add_parser("batch", help="run calibrate, diagnose, identify-legs or track over many datasets (local "
                                     "processes or a Dask cluster): one folder each, batch.yaml, fleet.html",
                       parents=[common], formatter_class=_DefaultsHelpFormatter)
    b.add_argument("batch_command", metavar="COMMAND", choices=("calibrate", "diagnose", "identify-legs", "track"),
                   help="calibrate, diagnose, identify-legs or track")
    b.add_argument("datasets", nargs="+", metavar="DATASET", help="dataset folders or glob patterns (quoted)")
    b.add_argument("--out", required=True, type=Path,
                   help="batch folder: one output folder per dataset, batch.yaml, fleet.html, fleet.csv")
    _add_executor_args(b)
    b.add_argument("--redo", action="store_true", help="run again the datasets whose output is already finished")
    b.add_argument("--legs", action="store_true", help="calibrate: also estimate the leg parameters")
    b.add_argument("--no-icp", action="store_true", help="track: proprioception only")

    st = sub.add_parser("study", help="Monte Carlo of a station program: simulate + calibrate over N seeds, "
                                      "accuracy and NEES per DoF (study.yaml, plots)", parents=[common],
                        formatter_class=_DefaultsHelpFormatter)
    st.add_argument("--robot", default="octopus", help="built-in robot model (octopus, qingzhui, messor, a1)")
    st.add_argument("--program", default="chai2015", help="station program (chai2015, labecki2012, random)")
    st.add_argument("--runs", type=int, default=20, help="simulated calibrations, one seed each")
    st.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed+runs-1")
    st.add_argument("--stations", type=int, default=None, help="number of stations (random program)")
    st.add_argument("--effect", action="append", type=_effect_arg, default=[],
                    help="hide an effect in every run: CAUSE or CAUSE:key=value,... (docs/simulation.md)")
    st.add_argument("--out", required=True, type=Path, help="study folder: study.yaml, runs.csv, plots")
    _add_executor_args(st)


def _add_executor_args(parser) -> None:
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="Dask scheduler, tcp://HOST:PORT (default: $DASK_SCHEDULER_ADDRESS; none: a local "
                             "process pool)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="local worker processes (default: the machine's CPUs); with --scheduler, the most "
                             "tasks in flight")


def _cmd_batch(args):
    from graphcal.commands import batch
    from graphcal.errors import GraphcalError

    for flag, given, owner in (("--legs", args.legs, "calibrate"), ("--no-icp", args.no_icp, "track")):
        if given and args.batch_command != owner:
            raise GraphcalError(f"batch {args.batch_command}: {flag} applies to {owner} only")
    options = {"calibrate": {"legs": args.legs or None}, "track": {"icp": False if args.no_icp else None}}
    return batch.run(args.batch_command, args.datasets, args.out, scheduler=args.scheduler, workers=args.workers,
                     redo=args.redo, options=options.get(args.batch_command), progress=not args.quiet)


def _cmd_study(args):
    from graphcal.commands import study

    return study.run(robot=args.robot, program=args.program, runs=args.runs, out_dir=args.out,
                     first_seed=args.first_seed, n_stations=args.stations, effects=args.effect,
                     scheduler=args.scheduler, workers=args.workers, progress=not args.quiet)


def _add_simulate_parser(sub, common) -> None:
    """The ``simulate`` subcommand's arguments."""
    s = sub.add_parser("simulate", help="simulate a calibration session and write it as a dataset", parents=[common],
                       formatter_class=_DefaultsHelpFormatter)
    s.add_argument("--robot", default=None,
                   help="built-in robot model (octopus, qingzhui, messor, a1); default: the walking program's own "
                        "robot, otherwise octopus")
    s.add_argument("--program", default="chai2015",
                   help="station program (chai2015, labecki2012, random), walk (tripod-walk, tripod-stairs: "
                        "the qingzhui's tripod gait; trot, walk: the a1 quadruped with foot-force sensors; 1 kHz "
                        "timeseries; see docs/state_estimation.md), or mocap "
                        "(a leg in the air in a motion-capture room, Yuan et al.'s set-up, for identify-legs; "
                        "--stations samples, default 1000; see docs/legs.md)")
    s.add_argument("--ground", default="level", help="level, bumpy-little, bumpy-big, stairs, boxes")
    s.add_argument("--real-like", action="store_true",
                   help="a walking program written as a real robot's log: 400 Hz, lying, standing up and lying down, "
                        "raw foot counts with per-foot offsets and gains, the IMU off the base link, noise drawn away "
                        "from graphcal's defaults (docs/simulation.md)")
    s.add_argument("--out", required=True, type=Path, help="output dataset folder (must not exist or be empty)")
    s.add_argument("--seed", type=int, default=0,
                   help="seed of every random draw (noise, random stations, effects without parameters); "
                        "the same seed writes the same dataset")
    s.add_argument("--stations", type=int, default=None, help="number of stations (random program)")
    s.add_argument("--sessions", type=int, default=1, help="number of stances (feet re-planted between them)")
    s.add_argument("--sensor", action="append", default=None, help="simulate only this sensor (repeatable)")
    s.add_argument("--output", choices=("clouds", "planes", "both"), default="both",
                   help="write raw clouds, fitted planes (planes.csv), or both (default); a laser "
                        "scanner's scans are written as clouds with every choice (a scan has no plane)")
    s.add_argument("--cloud-stride", type=int, default=None,
                   help="keep every k-th camera pixel row/column (1 = full 640x480 frames; default 4; "
                        "tripod-walk 16, tripod-stairs 8)")
    s.add_argument("--distance", type=float, default=None,
                   help="walking programs: body path length, m (tripod-walk default 20)")
    s.add_argument("--duration", type=float, default=None,
                   help="tripod-walk: walk about this long, s (instead of --distance)")
    s.add_argument("--cloud-rate", type=float, default=None,
                   help="walking programs: depth clouds per second (default 30; 0 = none)")
    s.add_argument("--cad-error-mm", type=float, default=None, metavar="MM",
                   help="walking programs: the depth camera's CAD prior in dataset.yaml is its true pose moved by a "
                        "draw of this spread per axis (default 0: the prior is the truth)")
    s.add_argument("--cad-error-deg", type=float, default=None, metavar="DEG",
                   help="walking programs: ... and rotated by a draw of this spread per axis (default 0)")
    s.add_argument("--camera-delay-ms", type=float, default=None, metavar="MS",
                   help="walking programs: every depth cloud stamped this late (default 0)")
    s.add_argument("--sway-deg", type=float, default=None, metavar="DEG",
                   help="walking programs: the body's roll sway amplitude at full speed (default 1; its pitch nod "
                        "is half of it)")
    s.add_argument("--leg-errors", action="store_true",
                   help="draw random joint-offset (0.5 deg) and link-length (3 mm) errors on every leg")
    s.add_argument("--effect", action="append", type=_effect_arg, default=[],
                   help="hide an effect: CAUSE or CAUSE:key=value,... (see docs/simulation.md); "
                        "CAUSE alone draws its magnitude and location from the seed")
    s.add_argument("--overwrite", action="store_true",
                   help="replace a previous simulation in --out (one with a graphcal truth.yaml and nothing else)")


def _cmd_simulate(args):
    import math

    from graphcal.commands import simulate

    walk = {key: scale * value for key, scale, value in (
        ("cad_error_m", 1e-3, args.cad_error_mm), ("cad_error_rad", math.pi / 180, args.cad_error_deg),
        ("camera_delay_s", 1e-3, args.camera_delay_ms), ("sway_rad", math.pi / 180, args.sway_deg)) if value is not None}
    if args.sway_deg is not None:
        walk["nod_rad"] = walk["sway_rad"] / 2
    return simulate.run(
        robot=args.robot,
        walk=walk,
        program=args.program,
        ground=args.ground,
        out_dir=args.out,
        seed=args.seed,
        n_stations=args.stations,
        n_sessions=args.sessions,
        sensors=tuple(args.sensor) if args.sensor else None,
        output=args.output,
        cloud_stride=args.cloud_stride,
        distance_m=args.distance,
        duration_s=args.duration,
        cloud_rate_hz=args.cloud_rate,
        real_like=args.real_like,
        leg_errors=args.leg_errors,
        effects=args.effect,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )


def _cmd_calibrate(args):
    from graphcal.clouds.plane_table import check_max_points
    from graphcal.commands import calibrate
    from graphcal.errors import GraphcalError

    if not (math.isfinite(args.ground_roughness_mm) and args.ground_roughness_mm >= 0):
        raise GraphcalError(f"--ground-roughness-mm must be a number >= 0 (mm), got {args.ground_roughness_mm}")
    offsets = {}
    for text in args.time_offset_ms:
        name, _, value = text.partition("=")
        try:
            ms = float(value)
        except ValueError:
            ms = float("nan")
        if not name or not math.isfinite(ms) or abs(ms) > 1000:
            raise GraphcalError(f"--time-offset-ms {text}: expected SENSOR=MS with MS a number of milliseconds "
                                "within +-1000 (e.g. depth=25)")
        offsets[name] = 1e-3 * ms
    return calibrate.run(args.dataset, args.out, legs=args.legs, incremental=args.incremental, time_offsets_s=offsets,
                         progress=not args.quiet, ground_roughness_m=1e-3 * args.ground_roughness_mm,
                         plane_max_points=check_max_points(args.plane_points, "--plane-points"),
                         noise_from=args.noise_from,
                         scene_max_points=None if args.scene_max_points == 0 else check_max_points(
                             args.scene_max_points, "--scene-max-points"))


def _cmd_suggest_poses(args):
    from graphcal.commands import suggest_poses

    return suggest_poses.run(args.dataset, args.k, out=args.out, after_existing=args.after_existing,
                             noise_from=args.noise_from, sigma_target_deg=args.sigma_target_deg,
                             sigma_target_mm=args.sigma_target_mm)


def _cmd_validate(args):
    from graphcal.commands import validate

    return validate.run(args.dataset)


def _cmd_extract_planes(args):
    from graphcal.commands import extract_planes

    return extract_planes.run(args.dataset, args.out, max_planes=args.max_planes, progress=not args.quiet,
                              max_points=args.plane_points, overwrite=args.overwrite)


def _cmd_diagnose(args):
    from graphcal.commands import diagnose

    return diagnose.run(args.dataset, args.out, progress=not args.quiet)


def _cmd_identify_legs(args):
    from graphcal.commands import identify_legs

    return identify_legs.run(args.dataset, args.out, progress=not args.quiet, mocap_free=args.mocap_free,
                             origins=args.origins, sigma_marker_mm=args.sigma_marker_mm,
                             sigma_joint_deg=args.sigma_joint_deg, robust=args.robust)


def _cmd_track(args):
    from graphcal.commands import track
    from graphcal.locomotion.estimator import TrackerConfig

    return track.run(args.dataset, args.out, progress=not args.quiet, tum_rate_hz=args.tum_rate,
                     config=TrackerConfig(icp=not args.no_icp), noise_file=args.noise,
                     learn_noise=not args.no_noise_learning)


def _cmd_plan_gait(args):
    from graphcal.commands import plan_gait
    from graphcal.errors import GraphcalError
    from graphcal.planning.climb import ClimbConfig

    if args.max_steps < 1:
        raise GraphcalError(f"--max-steps must be >= 1, got {args.max_steps}")
    if args.min_tread_points < 0:
        raise GraphcalError(f"--min-tread-points must be >= 0, got {args.min_tread_points}")
    return plan_gait.run(args.track_dir, args.out, dataset=args.dataset, start_time_s=args.start_time,
                         climb=ClimbConfig(max_steps=args.max_steps, min_tread_points=args.min_tread_points))


def _cmd_import(args):
    from graphcal.commands import import_log

    return import_log.run(args.log, args.out, map_path=args.map, urdf=args.urdf, receive_time=args.receive_time,
                          msg_dir=args.msg_dir, timeseries=args.timeseries, progress=not args.quiet,
                          overwrite=args.overwrite, cloud_rate_hz=args.cloud_rate)


#: the handler attached to the ``graphcal`` logger by :func:`configure_logging` (replaced on each call)
_HANDLER_MARK = "_graphcal_cli_handler"


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is when a message is emitted (tests
    and callers that redirect stderr after the command line was configured still get the lines)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def configure_logging(quiet: bool = False, verbose: bool = False) -> None:
    """Messages of every graphcal module (``logging.getLogger(__name__)``) go to stderr, one line each,
    as the message alone: warnings only with ``quiet``, everything with ``verbose`` (DEBUG), else INFO."""
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    logger = logging.getLogger("graphcal")
    for h in [h for h in logger.handlers if getattr(h, _HANDLER_MARK, False)]:
        logger.removeHandler(h)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    setattr(handler, _HANDLER_MARK, True)
    logger.addHandler(handler)
    logger.setLevel(level)


#: commands whose --out is an analysis of DATASET: it may not lie inside DATASET
_OUT_OUTSIDE_DATASET = ("calibrate", "diagnose", "identify-legs", "track")


@contextlib.contextmanager
def _output_guard(args):
    """SIGTERM stops the command cleanly (as Ctrl-C), and its --out is locked against a second
    command writing the same output, and refused inside the dataset it analyses."""
    from graphcal.io.atomic import check_output_outside, output_lock, sigterm_as_interrupt

    out = getattr(args, "out", None)
    with contextlib.ExitStack() as stack:
        stack.enter_context(sigterm_as_interrupt())
        if out is not None:
            if args.command in _OUT_OUTSIDE_DATASET:
                check_output_outside(out, args.dataset)
            stack.enter_context(output_lock(out))
        yield


def _refuse_unknown(parser: argparse.ArgumentParser, extra: list[str]) -> None:
    """An unknown flag of a command: that command's usage and the nearest flags it has (exit 2)."""
    import difflib
    import re

    flags = sorted(set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", parser.format_help())))
    bad = next((a for a in extra if a.startswith("-")), extra[0])
    close = difflib.get_close_matches(bad.split("=")[0], flags, n=3, cutoff=0.6)
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    parser.error(f"unrecognized argument{'s' if len(extra) > 1 else ''} {' '.join(extra)}{hint}")


def main(argv: list[str] | None = None) -> int:
    from graphcal.errors import GraphcalError

    _CommandParser.argv = list(sys.argv[1:] if argv is None else argv)
    args, extra = _build_parser().parse_known_args(argv)
    if extra:
        _refuse_unknown(args.subcommands[args.command], extra)
    configure_logging(args.quiet, args.verbose)
    handlers = {
        "simulate": _cmd_simulate,
        "track": _cmd_track,
        "validate": _cmd_validate,
        "calibrate": _cmd_calibrate,
        "suggest-poses": _cmd_suggest_poses,
        "extract-planes": _cmd_extract_planes,
        "identify-legs": _cmd_identify_legs,
        "diagnose": _cmd_diagnose,
        "import": _cmd_import,
        "plan-gait": _cmd_plan_gait,
        "batch": _cmd_batch,
        "study": _cmd_study,
    }
    try:
        with _output_guard(args):
            result = handlers[args.command](args)
            print(result.summary_text())
        return 0
    except GraphcalError as exc:
        print(f"graphcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        from graphcal.io.atomic import InterruptedAfterWrite, Terminated

        said = f"interrupted {exc}" if isinstance(exc, InterruptedAfterWrite) else "interrupted; nothing was written"
        print(f"graphcal {args.command}: {said}", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
    except BrokenPipeError:
        # the reader of stdout went away (``graphcal validate D | head -1``): stop quietly, as
        # command-line tools do (no traceback, nor one at exit when Python flushes stdout)
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
