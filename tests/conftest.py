"""Fixtures shared by the tests. Helpers the benches need too (numerical Jacobians, the simulated
calibration's truth and errors, the hexapod graphcal does not ship) live in graphcal/testing.py;
test modules never import each other.

Markers (pyproject.toml): ``slow`` marks the long end-to-end runs; ``pytest -m "not slow"`` is the
quick development subset, the full run (CI) includes them. ``battery`` marks the statistical
batteries among them (every battery is also slow): ``pytest -m "not battery"`` runs everything else.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

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
