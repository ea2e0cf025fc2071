"""Fixtures shared by the tests. Helpers the benches need too (numerical Jacobians, the simulated
calibration's truth and errors, the hexapod graphcal does not ship) live in graphcal/testing.py;
test modules never import each other.

Markers (pyproject.toml): ``slow`` marks the long end-to-end runs; ``pytest -m "not slow"`` is the
quick development subset, the full run (CI) includes them. ``battery`` marks the statistical
batteries among them (every battery is also slow): ``pytest -m "not battery"`` runs everything else.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

# One BLAS / OpenMP thread per test process, set before numpy is imported (here, and inherited by
# the pytest-xdist workers): the workers already share the cores, and a second BLAS thread per
# worker competes with them (a 350x350 Cholesky took 0.5 s instead of 1 ms on 2 busy cores);
# the batteries' worker pools do the same (examples/battery_pool.py).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


@pytest.fixture(scope="session")
def load_example():
    """``load(path, module_name=None)``: execute ``examples/<path>`` (e.g. ``"chai2015_reproduction.py"``,
    ``"octopus_chai2015/run.py"``) as a module and return it; the example's folder goes on
    ``sys.path`` so that it can import its siblings. The module is named after the file unless
    ``module_name`` is given."""

    def load(path: str, module_name: str | None = None):
        file = EXAMPLES / path
        if str(file.parent) not in sys.path:
            sys.path.insert(0, str(file.parent))
        spec = importlib.util.spec_from_file_location(module_name or file.stem, file)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    return load
