"""Corrupted datasets: read_dataset / validate_dataset either succeed or raise DatasetError, nothing else.

Random byte flips, truncations and insertions, and cell/token replacements with 'nan', 'inf', '',
'1e400', extreme finite numbers ('1e300', '1.7e308', '5e-324'), YAML aliases, text..., in
dataset.yaml, the CSV files and the PLY clouds (one ASCII, one binary) of the hand-made fixture
tests/data/octopus_small.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from graphcal.errors import DatasetError
from graphcal.io import read_dataset, validate_dataset, write_ply

FIXTURE = Path(__file__).parent / "data" / "octopus_small"
TARGETS = [
    "dataset.yaml",
    "stations.csv",
    "planes.csv",
    "mocap.csv",
    "timeseries.csv",
    "clouds/depth/1.ply",  # ASCII
    "clouds/depth/t10.01.ply",  # rewritten as binary below
]
REPLACEMENTS = ["nan", "inf", "-inf", "", "1e400", "-1e400", "abc", "1_0", " ", '"', ",", "0x10", "NaN", "1e-400",
                "-0", "999999999999999999999", "body.9", "..", "/etc/passwd", "\x00", "é", "[", ":", "- a",
                "1e300", "-1e300", "1.7e308", "1e15", "-1e15", "1e-300", "5e-324", "0", "1e6", "*a", "&a [1]"]  # fmt: skip

fraction = st.floats(min_value=0.0, max_value=1.0, exclude_max=True)
byte_op = st.one_of(
    st.tuples(st.just("flip"), fraction, st.integers(1, 255)),
    st.tuples(st.just("truncate"), fraction),
    st.tuples(st.just("insert"), fraction, st.one_of(
        st.binary(min_size=1, max_size=8),
        st.sampled_from([b",", b"\n", b'"', b"nan", b": ", b"[", b"-", b"\r", b"  ", b"#", b"\t", b"!!"]),
    )),  # fmt: skip
    st.tuples(st.just("cell"), fraction, fraction, st.one_of(st.sampled_from(REPLACEMENTS), st.text(max_size=6))),
)


def corrupt(data: bytes, op) -> bytes:
    """``data`` with one ``byte_op`` applied (also used by tests/test_fuzz_commands.py)."""
    kind = op[0]
    if kind == "flip":
        if not data:
            return data
        i = int(op[1] * len(data))
        return data[:i] + bytes([data[i] ^ op[2]]) + data[i + 1 :]
    if kind == "truncate":
        return data[: int(op[1] * len(data))]
    if kind == "insert":
        i = int(op[1] * (len(data) + 1))
        return data[:i] + op[2] + data[i:]
    # "cell": replace one comma/whitespace-separated token of one line
    lines = data.split(b"\n")
    r = int(op[1] * len(lines))
    sep = b"," if b"," in lines[r] else b" "
    cells = lines[r].split(sep)
    c = int(op[2] * len(cells))
    cells[c] = op[3].encode("utf-8", "surrogatepass")
    lines[r] = sep.join(cells)
    return b"\n".join(lines)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(target=st.sampled_from(TARGETS), ops=st.lists(byte_op, min_size=1, max_size=3))
def test_corrupted_dataset_raises_only_dataset_error(target, ops):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "ds"
        shutil.copytree(FIXTURE, d)
        pts = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.0, 0.1, 1.0], [0.1, 0.1, 1.1]])
        write_ply(d / "clouds/depth/t10.01.ply", pts, binary=True)
        f = d / target
        data = f.read_bytes()
        for op in ops:
            data = corrupt(data, op)
        f.write_bytes(data)
        for fn in (read_dataset, validate_dataset):
            try:
                fn(d)
            except DatasetError as exc:
                msg = str(exc)
                assert msg and "\n" not in msg, msg
                assert str(d) in exc.file, exc.file
