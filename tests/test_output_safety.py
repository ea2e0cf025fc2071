"""Output safety of the command line (issue 32): SIGTERM while the outputs are being written leaves
no hidden temporary folder, a second command writing the same --out is refused while the first
holds it, and an analysis is never written inside the dataset it reads."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from graphcal.cli import main
from graphcal.io.atomic import output_lock

DATA = Path(__file__).parent / "data" / "octopus_small"


@pytest.fixture()
def dataset(tmp_path):
    d = tmp_path / "ds"
    shutil.copytree(DATA, d)
    return d


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_out_inside_the_dataset_is_refused(dataset, capsys):
    before = _tree(dataset)
    assert main(["calibrate", str(dataset), "--out", str(dataset / "results"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "inside the dataset" in err[0] and "results" in err[0]
    assert _tree(dataset) == before  # nothing added, nothing changed


def test_a_second_command_on_a_locked_out_is_refused(dataset, tmp_path, capsys):
    out = tmp_path / "cal"
    with output_lock(out):
        assert main(["calibrate", str(dataset), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "being written by another graphcal command" in err and str(out) in err
    assert not out.exists()
    # the lock is released with its holder: the same command now runs, and leaves no lock file
    assert main(["calibrate", str(dataset), "--out", str(out), "--quiet"]) == 0
    assert (out / "calibration.yaml").is_file()
    assert not (tmp_path / ".cal.lock").exists()


def test_sigterm_while_writing_leaves_no_hidden_folder(dataset, tmp_path):
    """SIGTERM at the moment the hidden output folder exists: the command ends with 143 and one line,
    the hidden folder is removed, and no output appears."""
    out = tmp_path / "cal"
    proc = subprocess.Popen([sys.executable, "-m", "graphcal", "calibrate", str(dataset), "--out", str(out),
                             "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    hidden = []
    while proc.poll() is None and time.monotonic() < deadline and not hidden:
        hidden = [p for p in tmp_path.iterdir() if p.name.startswith(".cal.tmp-")]
        time.sleep(0.002)
    assert hidden, "the command finished before its hidden output folder was seen"
    os.kill(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert err.strip().splitlines() == ["graphcal calibrate: interrupted; nothing was written"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".cal")] == []
    assert not out.exists()
