"""The bookkeeping battery of ``graphcal diagnose`` (issue 29): datasets with one bookkeeping error
hidden (graphcal/simulation/bookkeeping.py), diagnosed blind, scored against the truth.

Each case: a robot, the ``random`` program with 48 stations in 3 sessions (turned by 40 deg), planes
only, and one error of a kind drawn from the seed -- two stations' sensor data exchanged, a sensor
row filed under another station, two legs' joint columns exchanged, one normal component's sign
flipped, a plane in the opposite convention, a distance in millimetres, an undeclared height step
(mid-run, at the first or last 1-2 stations) or an undeclared knock of the extrinsic (mid-run, 1-2
stations from either end) -- or nothing (clean). The dataset folder holds no truth; the truth is
read after the diagnosis (``<case>.truth.yaml`` beside it).

Scoring (:func:`score`):

* **found**: a correction of ``diagnose`` (``diagnosis.json`` "corrections") names the hidden cause
  at its place (stations, sensor, legs, component as the truth has them; the first station of the
  new state for height steps and knocks, exactly: at 10-35 mm and 1.5-3 deg every station tells);
  for a knock an ``extrinsic_change`` finding at the station and sensor counts too, for a height step
  a ``session_offset`` finding whose place names the station;
* **noted**: the case is *ambiguous* (a knock with one station on one side of it, the first or the
  last: an outlier station reads the same, so no data can tell the cause; a one-station height step
  is not ambiguous: it moves the plane distance alone) and nothing wrong is
  corrected, but a note of the diagnosis names that station (or a correction there lists its
  alternatives): the honest answer there. An ``outlier_stations`` finding alone is not a note (it
  names one cause and not the other);
* **refused**: the dataset reader refuses the file (a millimetre slip of a plane ~1 m away reads
  d > 100 m: "looks like millimetres", the row named) -- not a correction;
* **missed**: anything else.

A **false alarm** is any correction on clean data. A **confident wrong** answer is a correction
that does not match the truth and lists no alternative (``Correction.alternatives`` empty).

Hold-out discipline: the DEVELOPMENT set (kinds :data:`graphcal.simulation.bookkeeping.DEV_KINDS`,
seeds from 1000, octopus and qingzhui alternating) is what the finders are built against; the BLIND
set (kinds ``BLIND_KINDS``: stations exchanged far apart, mirrored legs, the second-largest normal
component's sign, centimetres; seeds from 7000; octopus, qingzhui and the custom hexapod of
graphcal/testing.py in turn) is run once, at the end.

Run: ``python examples/diagnosis_bookkeeping.py [--set dev|blind] [--per 4] [--clean 20] [--jobs 1] [--cache DIR]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DEV_ROBOTS = ("octopus", "qingzhui")
BLIND_ROBOTS = ("octopus", "qingzhui", "sidewinder")
DEV_FIRST_SEED = 1000
BLIND_FIRST_SEED = 7000
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "graphcal-bookkeeping-cache"


@dataclass(frozen=True)
class BookCase:
    seed: int
    robot: str
    kind: str
    truth: dict
    outcome: str  # "found", "noted", "refused", "missed" (or "clean" / "false_alarm" for clean data)
    corrections: tuple  # labels of the corrections made
    confident_wrong: bool
    detail: str
    seconds: float

    @property
    def right(self) -> bool:
        """Found, or (ambiguous cases) honestly noted; clean: nothing corrected."""
        return self.outcome in ("found", "noted", "clean")


def _ints(v) -> set:
    if isinstance(v, (list, tuple)):
        return {int(x) for x in v}
    return {int(v)} if v is not None else set()


def _named_stations(where: dict) -> set:
    out = set()
    for k in ("station", "stations", "from_station"):
        out |= _ints(where.get(k))
    return out


def _same_legs(named, truth) -> bool:
    def norm(names, feet):
        out = set()
        for n in names:
            hits = [f for f in feet if f == n or f.startswith(str(n) + "_")]
            out.add(hits[0] if len(hits) == 1 else str(n))
        return out

    return len(named) == 2 and norm(named, truth) == set(truth)


def matches(truth: dict, cause: str, where: dict) -> bool:
    """Does a correction (or finding) of ``cause`` at ``where`` name the hidden error ``truth``
    (:meth:`BookkeepingTruth.to_dict`) at its place?"""
    t, tw = truth["cause"], truth["where"]
    if "sensor" in tw and where.get("sensor") not in (None, tw["sensor"]):
        return False
    if t == "extrinsic_knock":
        return cause in ("extrinsic_knock", "extrinsic_change") and (
            _ints(where.get("from_station")) or _ints(where.get("station"))) == {tw["from_station"]}
    if t == "height_step":
        if cause not in ("height_step", "session_offset"):
            return False
        return _ints(where.get("from_station")) == {tw["from_station"]} or _ints(where.get("stations")) == set(tw["stations"])
    if cause != t:
        return False
    if t == "legs_exchanged":
        return _same_legs(list(where.get("legs", ())), tw["legs"])
    if t in ("stations_exchanged", "station_mislabelled"):
        return _named_stations(where) == set(tw["stations"])
    if t == "normal_sign" and where.get("component") not in (None, tw["component"]):
        return False
    return _named_stations(where) == {tw["station"]}  # normal_sign, plane_convention, distance_unit


def _odd_station(truth: dict) -> int | None:
    """The one station whose state differs, in an ambiguous case."""
    k = int(truth["where"]["from_station"])
    return k - 1 if k <= 2 else k  # a knock at station 2: station 1 is the odd one; at the last: itself


def score(truth: dict, doc: dict) -> tuple[str, bool, str]:
    """(outcome, confident wrong, detail) of a diagnosis (``diagnosis.json`` as a dict) against the truth."""
    corr = doc.get("corrections", [])
    labels = [f"{c['cause']}{c['where']}" for c in corr]
    if not truth["cause"]:
        return ("false_alarm" if corr else "clean"), any(not c["alternatives"] for c in corr), f"corrections {labels}"
    good = [c for c in corr if matches(truth, c["cause"], c["where"])]
    wrong = [c for c in corr if c not in good]
    cw = any(not c["alternatives"] for c in wrong)
    found_by = [f"{f['cause']}{f['where']}" for f in doc.get("findings", [])
                if f["cause"] in ("extrinsic_change", "session_offset") and matches(truth, f["cause"], f["where"])]
    detail = (f"corrections {labels}; findings {[f['cause'] + str(f['where']) for f in doc.get('findings', [])]}"
              f"; notes {[n[:90] for n in doc.get('notes', []) if 'station' in n][:3]}")
    if good or found_by:
        return "found", cw, detail
    if truth.get("ambiguous") and not wrong:
        st = _odd_station(truth)
        said = [n for n in doc.get("notes", []) if f"station {st}" in n or f"stations [{st}" in n]
        hedged = [c for c in corr if st in _named_stations(c["where"]) and c["alternatives"]]
        if said or hedged:
            return "noted", cw, detail
    return "missed", cw, detail


def _custom_robot(robot: str):
    if robot != "sidewinder":
        return None
    from graphcal.testing import custom_hexapod

    return custom_hexapod()


def run_case(seed: int, robot: str, kind: str, cache: Path, workdir: Path) -> BookCase:
    from graphcal.diagnosis import diagnose
    from graphcal.errors import DatasetError
    from graphcal.report.diagnosis_json import diagnosis_to_dict
    from graphcal.simulation.bookkeeping import make_case

    out = Path(workdir) / f"book_{seed}_{robot}_{kind}"
    truth = make_case(kind, robot, seed, Path(cache), out, custom_robot=_custom_robot(robot)).to_dict()
    t0 = time.perf_counter()
    try:
        doc = diagnosis_to_dict(diagnose(out))
    except DatasetError as exc:
        return BookCase(seed, robot, kind, truth, "refused", (), False, f"DatasetError: {str(exc)[-160:]}",
                        time.perf_counter() - t0)
    seconds = time.perf_counter() - t0
    outcome, cw, detail = score(truth, doc)
    labels = tuple(f"{c['cause']}{c['where']}" for c in doc.get("corrections", []))
    return BookCase(seed, robot, kind, truth, outcome, labels, cw, detail, seconds)


def cases(kinds, per: int, clean: int, first_seed: int, robots) -> list[tuple[int, str, str]]:
    """(seed, robot, kind): ``per`` cases of each kind but "clean", then ``clean`` clean cases, one
    seed each; each kind's cases go to the robots in turn (round r, kind k: robot (r + k) mod n)."""
    out, seed = [], first_seed
    for r in range(per):
        for k, kind in enumerate(x for x in kinds if x != "clean"):
            out.append((seed, robots[(r + k) % len(robots)], kind))
            seed += 1
    for _ in range(clean):
        out.append((seed, robots[seed % len(robots)], "clean"))
        seed += 1
    return out


def _run_one(args):
    seed, robot, kind, cache, workdir = args
    try:
        return run_case(seed, robot, kind, Path(cache), Path(workdir))
    except Exception as exc:  # a crash is a failed case, reported with the others
        import traceback

        return BookCase(seed, robot, kind, {}, "error", (), False,
                        f"{type(exc).__name__}: {exc} | {traceback.format_exc(limit=4)[-400:]}", 0.0)


def summarize(results: list[BookCase]) -> dict:
    """found (right place and cause), right (found or honestly noted), false alarms, confident wrong,
    per kind, and the mean diagnose time of the clean cases (s)."""
    effect = [r for r in results if r.kind != "clean"]
    clean = [r for r in results if r.kind == "clean"]
    per_kind = {}
    for r in results:
        k = per_kind.setdefault(r.kind, {"n": 0, "found": 0, "right": 0, "confident_wrong": 0})
        k["n"] += 1
        k["found"] += r.outcome in ("found", "clean")
        k["right"] += r.right
        k["confident_wrong"] += r.confident_wrong
    return {
        "cases": len(effect), "clean": len(clean),
        "found": float(np.mean([r.outcome == "found" for r in effect])) if effect else float("nan"),
        "right": float(np.mean([r.right for r in effect])) if effect else float("nan"),
        "false_alarm": float(np.mean([r.outcome == "false_alarm" for r in clean])) if clean else float("nan"),
        "confident_wrong": float(np.mean([r.confident_wrong for r in results])) if results else float("nan"),
        "errors": int(sum(r.outcome == "error" for r in results)),
        "refused": int(sum(r.outcome == "refused" for r in results)),
        "clean_seconds": float(np.mean([r.seconds for r in clean])) if clean else float("nan"),
        "per_kind": per_kind,
    }


def overhead(n: int = 10, cache: Path = DEFAULT_CACHE, first_seed: int = DEV_FIRST_SEED + 500) -> dict:
    """CPU time of the bookkeeping stage (:func:`graphcal.diagnosis.bookkeeping.find_bookkeeping`)
    within ``diagnose`` on ``n`` clean datasets (DEV robots in turn): {"diagnose_s", "bookkeeping_s",
    "share"} (means over the datasets, CPU seconds of this process)."""
    import graphcal.diagnosis.bookkeeping as bk_module
    from graphcal.diagnosis import diagnose
    from graphcal.simulation.bookkeeping import make_case

    spent = []
    original = bk_module.find_bookkeeping

    def timed(model, say, **kwargs):
        t0 = time.process_time()
        try:
            return original(model, say, **kwargs)
        finally:
            spent.append(time.process_time() - t0)

    total, book = [], []
    bk_module.find_bookkeeping = timed
    try:
        with tempfile.TemporaryDirectory(prefix="graphcal-bookkeeping-") as tmp:
            for i in range(n):
                out = Path(tmp) / f"clean_{i}"
                make_case("clean", DEV_ROBOTS[i % len(DEV_ROBOTS)], first_seed + i, Path(cache), out)
                spent.clear()
                t0 = time.process_time()
                diagnose(out)
                total.append(time.process_time() - t0)
                book.append(sum(spent))
    finally:
        bk_module.find_bookkeeping = original
    return {"diagnose_s": float(np.mean(total)), "bookkeeping_s": float(np.mean(book)),
            "share": float(np.sum(book) / np.sum(total))}


def main(which: str = "dev", per: int = 4, clean: int = 20, jobs: int = 1, cache: Path = DEFAULT_CACHE, kinds=None,
         verbose: bool = True, json_out: Path | None = None) -> dict:
    """Run the DEVELOPMENT (``dev``) or BLIND (``blind``) battery: ``per`` cases of each kind and
    ``clean`` clean ones; returns {"results": [BookCase], **:func:`summarize`}."""
    from graphcal.simulation.bookkeeping import BLIND_KINDS, DEV_KINDS

    if which == "dev":
        todo = cases(kinds or DEV_KINDS, per, clean, DEV_FIRST_SEED, DEV_ROBOTS)
    elif which == "blind":
        todo = cases(kinds or BLIND_KINDS, per, clean, BLIND_FIRST_SEED, BLIND_ROBOTS)
    else:
        raise ValueError(f"--set must be dev or blind, got {which!r}")
    with tempfile.TemporaryDirectory(prefix="graphcal-bookkeeping-") as tmp:
        args = [(s, r, k, str(cache), tmp) for s, r, k in todo]
        from battery_pool import run_cases

        results = run_cases(_run_one, args, jobs)
    summary = summarize(results)
    if verbose:
        for r in results:
            print(f"{r.outcome:11s}{' CW' if r.confident_wrong else '   '} seed {r.seed} {r.robot:10s} {r.kind:22s} "
                  f"{r.seconds:5.1f} s  truth {r.truth.get('where', {})}  {r.detail}")
        for k, v in summary["per_kind"].items():
            print(f"  {k:22s} {v['found']}/{v['n']} found, {v['right']}/{v['n']} right, {v['confident_wrong']} confident wrong")
        print(f"bookkeeping battery ({which.upper()}): {summary['cases']} cases, {summary['clean']} clean: found "
              f"{summary['found']:.1%}, found or honestly noted {summary['right']:.1%}, false alarms "
              f"{summary['false_alarm']:.1%}, confident wrong {summary['confident_wrong']:.1%}, refused by the reader "
              f"{summary['refused']}, errors {summary['errors']}; clean diagnose {summary['clean_seconds']:.2f} s")
    if json_out is not None:
        Path(json_out).write_text(json.dumps({"set": which, "per": per, **summary,
                                              "results": [asdict(r) for r in results]}, indent=1, default=str))
    return {"results": results, **summary}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="dev", choices=("dev", "blind"))
    ap.add_argument("--per", type=int, default=4)
    ap.add_argument("--clean", type=int, default=20)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--kinds", default="", help="comma-separated subset of the set's kinds")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--overhead", type=int, default=0, help="only measure the bookkeeping stage's CPU share "
                    "of diagnose on this many clean datasets")
    a = ap.parse_args()
    if a.overhead:
        o = overhead(a.overhead, a.cache)
        print(f"clean data, {a.overhead} datasets: diagnose {o['diagnose_s']:.3f} s CPU, of which the bookkeeping "
              f"stage {o['bookkeeping_s']:.3f} s ({o['share']:.1%})")
        raise SystemExit(0)
    main(a.set, a.per, a.clean, a.jobs, a.cache, tuple(a.kinds.split(",")) if a.kinds else None, json_out=a.json)
