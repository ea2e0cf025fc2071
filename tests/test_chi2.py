"""graphcal.stats (scipy.special) against scipy.stats.chi2, and the calibrate path free of scipy.stats
(importing it cost ~1 s of every `graphcal calibrate`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2 as reference

from graphcal import stats as chi2


@pytest.mark.parametrize("dof", [0.5, 1, 2.7, 3, 6, 52, 1000])
def test_matches_scipy_stats(dof):
    q = np.array([0.05, 0.5, 0.95, 0.999, 1 - 1e-7])
    np.testing.assert_allclose(chi2.ppf(q, dof), reference.ppf(q, dof), rtol=1e-12)
    np.testing.assert_allclose(chi2.isf(1 - q, dof), reference.isf(1 - q, dof), rtol=1e-9)
    x = np.array([0.01, 1.0, dof, 3.0 * dof + 5.0])
    np.testing.assert_allclose(chi2.sf(x, dof), reference.sf(x, dof), rtol=1e-12)
    assert chi2.ppf(0.999, [3, 6]).shape == (2,)  # broadcasts like scipy's
    np.testing.assert_allclose(chi2.logsf(x, dof), reference.logsf(x, dof), rtol=1e-12, atol=1e-15)
    assert chi2.logsf(1e4, dof) == reference.logsf(1e4, dof) == -np.inf  # both underflow alike


def test_calibrate_and_its_incremental_mode_do_not_import_scipy_stats(tmp_path):
    """Both modes run on the small fixture (outlier screen, Huber thresholds, noise report, change
    test), then scipy.stats must still be absent."""
    data = Path(__file__).parent / "data" / "octopus_small"
    code = ("import sys; from graphcal.cli import main; "
            f"assert main(['calibrate', {str(data)!r}, '--out', {str(tmp_path / 'b')!r}, '--quiet']) == 0; "
            f"assert main(['calibrate', {str(data)!r}, '--out', {str(tmp_path / 'i')!r}, '--incremental', "
            "'--quiet']) == 0; print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False"
