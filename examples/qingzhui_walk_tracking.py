"""EKF mode on the qingzhui (Zhao et al. 2020): simulate the 20 m level walk and the stairs sequence
with ``graphcal simulate --program tripod-walk|tripod-stairs``, track both with ``graphcal track``
and print the accuracy and consistency numbers of docs/state_estimation.md.

Run:  python examples/qingzhui_walk_tracking.py [OUT_DIR] [--seeds N]
``main`` returns the numbers (a dict per sequence and seed); tests/test_examples.py runs this
example (seed 0) and asserts them, tests/test_track.py runs the same sequences through the command
line (fewer clouds), tests/test_ekf.py the Monte Carlo NEES on shorter walks.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

KEYS = ("distance_m", "drift_percent", "ape_rmse_m", "rpe_rmse_m", "nees_mean", "nees_fraction_in_band",
        "stance_nis_mean", "icp_updates", "icp_rejected", "icp_nis_mean", "icp_dof_mean", "real_time_factor")


def main(out_dir: str | Path | None = None, *, seeds=(0,), distance_m: float = 20.0, cloud_rate_hz: float = 10.0,
         progress: bool = False) -> dict:
    """Simulate and track the level walk (``distance_m``) and the stairs for each seed.

    Returns:
        {"level": {seed: metrics}, "stairs": {seed: metrics}} with the keys of ``KEYS`` (SI units,
        drift in %), plus "whiteness_fraction_inside" per run.
    """
    from graphcal.commands.track import run as run_track
    from graphcal.simulation.write import simulate_walking_to_folder

    root = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="graphcal-walk-"))
    out: dict = {"level": {}, "stairs": {}}
    for seed in seeds:
        for name, program, dist in (("level", "tripod-walk", distance_m), ("stairs", "tripod-stairs", None)):
            ds = root / f"{name}-{seed}"
            print(simulate_walking_to_folder(program=program, out_dir=ds, seed=seed, distance_m=dist,
                                             cloud_rate_hz=cloud_rate_hz, overwrite=True, progress=progress))
            print(run_track(ds, root / f"{name}-{seed}-track", progress=progress).summary_text())
            m = json.loads((root / f"{name}-{seed}-track" / "metrics.json").read_text())
            row = {k: m.get(k) for k in KEYS}
            row["whiteness_fraction_inside"] = m["innovation_whiteness"]["fraction_inside"]
            out[name][seed] = row
    return out


def _print(out: dict) -> None:
    for name, runs in out.items():
        for seed, m in runs.items():
            print(f"{name} seed {seed}: distance {m['distance_m']:.2f} m, drift {m['drift_percent']:.3f} %, "
                  f"APE {1e3 * m['ape_rmse_m']:.2f} mm, RPE {1e3 * (m['rpe_rmse_m'] or float('nan')):.2f} mm, "
                  f"NEES {m['nees_mean']:.2f} (in band {m['nees_fraction_in_band']:.2f}), stance NIS "
                  f"{m['stance_nis_mean']:.2f}/9, whiteness {m['whiteness_fraction_inside']:.3f}, ICP "
                  f"{m['icp_updates']} fused / {m['icp_rejected']} rejected, RTF {m['real_time_factor']:.1f}")


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    n = int(sys.argv[sys.argv.index("--seeds") + 1]) if "--seeds" in sys.argv else 1
    if "--seeds" in sys.argv:
        args = [a for a in args if a != str(n)]
    _print(main(args[0] if args else None, seeds=tuple(range(n))))
