"""graphcal's own exceptions. The command line prints them as one line and exits with code 2;
any other exception is a bug and is shown with its traceback."""

from __future__ import annotations

from pathlib import Path


def excerpt(text: str, limit: int = 80) -> str:
    """``text`` for a message: shown as it is when printable, else with its control characters
    escaped (as in a repr), cut to ``limit`` characters: a value read from a file never reaches the
    terminal raw (no escape sequence, no NUL, no page of someone else's file)."""
    text = str(text)
    if not text.isprintable():
        text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class GraphcalError(Exception):
    """Base class of every error graphcal raises on purpose (bad input, impossible request)."""


class DatasetError(GraphcalError):
    """A dataset (or a file given to graphcal) does not follow the contract.

    Args:
        file: the file at fault (path as the user gave it, or relative to the dataset folder).
        where: the row, column or key, e.g. ``"row 12, column q_lf_hip"`` or ``"sensors.depth.type"``.
        expected: what the contract asks for there.
        got: what was found (optional, shown verbatim, truncated).
    """

    def __init__(self, file: str | Path, where: str, expected: str, got: object | None = None):
        self.file = str(file)
        self.where = where
        self.expected = expected
        self.got = got
        msg = f"{self.file}: {excerpt(where, 120)}: expected {expected}"
        if got is not None:
            msg += f", got {excerpt(repr(got) if not isinstance(got, str) else got, 80)}"
        super().__init__(msg)

    def __reduce__(self):
        # pickled with its fields (the default passes only the message, which __init__ does not
        # take): a DatasetError raised in a worker process reaches the caller as itself
        return type(self), (self.file, self.where, self.expected, self.got)


class ModelError(GraphcalError):
    """A robot model (URDF, built-in model name, frame or joint) cannot be used as asked."""
