"""What every ``graphcal.commands.<name>.run(...)`` returns: a frozen dataclass with the library's
result, the files written, the warnings, the verdict where the command has one, and
``summary_text()``, the text the command line prints (:mod:`graphcal.cli`). Tests and callers read
the fields; only the console reads the text."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

__all__ = ["CommandResult", "folder_files"]


@runtime_checkable
class CommandResult(Protocol):
    """The fields every command result has (each one a frozen dataclass in its command's module)."""

    #: the paths the command wrote (empty when it wrote nothing)
    files: tuple[Path, ...]
    #: the warnings it found, one sentence each, without the ``warning:`` prefix
    warnings: tuple[str, ...]
    #: the command's verdict (calibrate: the model's adequacy, track: the filter's consistency, ...),
    #: or None where it has none
    verdict: str | None

    def summary_text(self) -> str:
        """The summary the command line prints (stdout)."""


def folder_files(folder: str | Path) -> tuple[Path, ...]:
    """The entries of ``folder`` (files and sub-folders, sorted by name), as written by a command."""
    return tuple(sorted(Path(folder).iterdir(), key=lambda p: p.name))
