"""The open-world battery of ``graphcal diagnose``: effects OUTSIDE its catalogue.

Each case simulates a dataset hiding one physical effect the catalogue has no cause for
(graphcal/simulation/effects.py :class:`OpenWorld`), diagnoses the folder blind (diagnose never
opens truth.yaml) and classifies the answer:

* ``structure``: diagnose says structure remains (a measurement group fails at physical noise, or
  a named cause is tentative: its held-out gain is not significant) -- the honest answer;
* ``wrong``: a catalogued cause named, supported, and no structure remains -- a confident wrong
  cause;
* ``silent``: nothing named and no structure (the effect did not show at this magnitude).

Generators (magnitudes and locations drawn from the seed):

* ``plate``: a plate 10-30 mm thick under two feet in one session (developed against);
* ``range_quadratic``: a depth error growing with range^2, k = 0.005-0.015 /m (developed against);
* ``sinking``: the feet sink steadily by 10-30 mm during one session (BLIND: run once, at the end);
* ``imu_drift``: the IMU mount tilts by 1-3 deg over the run, a mount warming up (BLIND).

Run: ``python examples/diagnosis_openworld.py [--generators plate,range_quadratic] [--per 5] [--jobs 2]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

ROBOTS = ("octopus", "qingzhui")
GENERATORS = ("plate", "range_quadratic", "sinking", "imu_drift")
DEVELOPED = ("plate", "range_quadratic")
BLIND = ("sinking", "imu_drift")
N_STATIONS = 48
N_SESSIONS = 3
HEADING_STEP_DEG = 40.0


@dataclass(frozen=True)
class OpenCase:
    seed: int
    robot: str
    generator: str
    truth: dict
    named: tuple  # the causes named (supported or not)
    outcome: str  # "structure", "wrong" or "silent"
    detail: str
    seconds: float


def draw(generator: str, rng: np.random.Generator, robot, sensors: tuple, sessions: tuple):
    """The :class:`OpenWorld` effect of ``generator`` at a magnitude and location drawn from ``rng``."""
    from graphcal.simulation.effects import OpenWorld

    session = str(rng.choice(sessions))
    if generator == "plate":
        feet = tuple(str(f) for f in rng.choice(list(robot.feet), size=2, replace=False))
        return OpenWorld(plate=(session, feet, float(rng.uniform(0.010, 0.030))))
    if generator == "range_quadratic":
        return OpenWorld(range_quadratic={str(rng.choice(sensors)): float(rng.uniform(0.005, 0.015))})
    if generator == "sinking":
        return OpenWorld(sinking={session: float(rng.uniform(0.010, 0.030))})
    if generator == "imu_drift":
        return OpenWorld(imu_drift=(float(np.radians(rng.uniform(1.0, 3.0))), float(rng.uniform(-np.pi, np.pi))))
    raise ValueError(generator)


def run_case(seed: int, robot_name: str, generator: str, workdir: Path) -> OpenCase:
    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict
    from graphcal.simulation.effects import Effects
    from graphcal.simulation.session import SimulationConfig, robot_and_info, simulate
    from graphcal.simulation.write import write_simulation

    t0 = time.perf_counter()
    out = workdir / f"open_{seed}_{robot_name}_{generator}"
    base = SimulationConfig(robot=robot_name, program="random", ground="level", seed=seed, n_stations=N_STATIONS,
                            n_sessions=N_SESSIONS, cloud_stride=8, session_heading_step_deg=HEADING_STEP_DEG)
    robot, info = robot_and_info(base)
    rng = np.random.default_rng([seed, GENERATORS.index(generator)])
    ow = draw(generator, rng, robot, tuple(info.sensors), tuple(f"s{k + 1}" for k in range(N_SESSIONS)))
    from dataclasses import replace

    result = simulate(replace(base, effects=Effects(open_world=ow)))
    write_simulation(result, out, output="planes", overwrite=True)
    doc = diagnosis_to_dict(diagnose(out))
    named = tuple(f["cause"] for f in doc["findings"])
    if doc["unexplained_structure"]:
        outcome = "structure"
    elif named:
        outcome = "wrong"
    else:
        outcome = "silent"
    detail = (f"named {list(named)}; structure in {doc['structure_remains_in']}; answer {doc['answer']}; "
              f"tentative {[f['cause'] for f in doc['findings'] if not f['supported']]}")
    return OpenCase(seed, robot_name, generator, ow.to_dict(), named, outcome, detail, time.perf_counter() - t0)


def cases(generators, per: int, first_seed: int = 500) -> list[tuple[int, str, str]]:
    out = []
    seed = first_seed
    for _ in range(per):
        for g in generators:
            out.append((seed, ROBOTS[seed % 2], g))
            seed += 1
    return out


def _run_one(args):
    seed, robot, generator, workdir = args
    try:
        return run_case(seed, robot, generator, Path(workdir))
    except Exception as exc:  # a crash is reported with the others (outcome "error")
        return OpenCase(seed, robot, generator, {}, (), "error", f"{type(exc).__name__}: {exc}", 0.0)


def main(generators=DEVELOPED, per: int = 5, jobs: int = 2, first_seed: int = 500, verbose: bool = True) -> dict:
    """Run the battery on ``generators``; returns {"results", "honest" (structure share), "wrong",
    "silent"} (shares over the cases)."""
    todo = cases(generators, per, first_seed)
    with tempfile.TemporaryDirectory(prefix="graphcal-openworld-") as tmp:
        args = [(s, r, g, tmp) for s, r, g in todo]
        from battery_pool import run_cases

        results = run_cases(_run_one, args, jobs)
    share = {k: float(np.mean([r.outcome == k for r in results])) for k in ("structure", "wrong", "silent", "error")}
    if verbose:
        for r in results:
            print(f"{r.outcome:9s} seed {r.seed} {r.robot:8s} {r.generator:16s} {r.seconds:5.1f} s  {r.truth}  {r.detail}")
        print(f"open world ({', '.join(generators)}): {len(results)} cases: structure reported {share['structure']:.0%}, "
              f"confident wrong {share['wrong']:.0%}, silent {share['silent']:.0%}, errors {share['error']:.0%}")
    return {"results": results, "honest": share["structure"], "wrong": share["wrong"], "silent": share["silent"],
            "error": share["error"]}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generators", default=",".join(DEVELOPED))
    ap.add_argument("--per", type=int, default=5)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=500)
    a = ap.parse_args()
    main(tuple(a.generators.split(",")), a.per, a.jobs, a.first_seed)
