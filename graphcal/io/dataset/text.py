"""Text of the dataset reader: a file's bytes decoded, and the pieces of a :class:`DatasetError`'s
message (a cell shown verbatim or as its repr, one line, a value shown short, a did-you-mean)."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Iterable

from graphcal.errors import DatasetError

#: what a check says of a value far too large to be in metres
MILLIMETRES_HINT = "looks like millimetres; the contract uses metres"


def did_you_mean(name: str, candidates: Iterable[str]) -> str:
    """`` (did you mean 'a', 'b'?)`` with up to three of ``candidates`` close to ``name``, or ``""``."""
    close = difflib.get_close_matches(name, list(candidates), n=3, cutoff=0.6)
    return f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""


def cell_text(text: str) -> str:
    """A cell or token for a message: verbatim if printable, else its repr (one line, visible)."""
    return text if text.isprintable() else repr(text)


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines included) made one space."""
    return " ".join(str(text).split())


def shown_value(v: object) -> str:
    """A value read from YAML for a message: its repr, cut to 60 characters (None: "nothing (null)")."""
    if v is None:
        return "nothing (null)"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def decode_utf8(raw: bytes, path: Path) -> str:
    """The text of file ``path`` (its bytes ``raw``, UTF-8 with or without a BOM); DatasetError naming
    the line and byte of the first invalid byte."""
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DatasetError(path, f"line {line} (byte {exc.start})", "UTF-8 text",
                           f"byte 0x{raw[exc.start]:02x}") from None  # fmt: skip
