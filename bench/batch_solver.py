"""graphcal's Python-driven LM against gtsam's LevenbergMarquardtOptimizer on the same graph of
1,000 Point3 variables and ~2,000 Python CustomFactors (engineering notes: gtsam copies the whole
Values into every Python callback), run side by side in this process.

    .venv/bin/python bench/batch_solver.py
"""

from __future__ import annotations

import time

import gtsam

from graphcal.solvers.batch import solve_lm
from graphcal.testing import custom_point_graph, max_local_difference  # the graph tests/test_batch_solver.py solves


def main() -> None:
    graph, initial = custom_point_graph()
    t0 = time.perf_counter()
    res = solve_lm(graph, initial)
    t_ours = time.perf_counter() - t0
    p = gtsam.LevenbergMarquardtParams()
    p.setRelativeErrorTol(1e-9)
    p.setAbsoluteErrorTol(1e-12)
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, p)
    ref = opt.optimize()
    t_gtsam = time.perf_counter() - t0
    print(f"{graph.size()} Python CustomFactors: solve_lm {t_ours:.2f} s ({res.iterations} iterations), "
          f"gtsam LM {t_gtsam:.2f} s ({opt.iterations()} iterations), ratio {t_gtsam / t_ours:.1f}x, "
          f"max |difference| {max_local_difference(ref, res.values):.1e}")


if __name__ == "__main__":
    main()
