"""Input files read whole, and only when they are regular files.

A named pipe (FIFO) given where a file is expected would block a reader forever, and a device
(``/dev/zero``, ``/dev/urandom``) would never end: :func:`read_regular_file` looks at what a path is
before opening it, refuses anything but a regular file by name, and opens without blocking (then
checks the opened file again, so a path swapped in between is caught too)."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["file_kind", "read_regular_file", "check_regular_file"]


def file_kind(mode: int) -> str:
    """What an ``st_mode`` describes, for a message (``"a named pipe (FIFO)"``, ``"a folder"``...)."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _refused(path: Path, mode: int) -> OSError:
    return OSError(errno.EINVAL, f"{file_kind(mode)}, not a regular file (refused without opening it)", str(path))


def check_regular_file(path: str | Path) -> None:
    """OSError (its ``strerror`` says what the path is) unless ``path`` (links followed) is a regular
    file; FileNotFoundError and the like as :func:`os.stat` raises them."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise _refused(Path(path), st.st_mode)


def read_regular_file(path: str | Path) -> bytes:
    """The bytes of the regular file ``path`` (links followed). OSError for anything else: missing,
    unreadable, or not a regular file (FIFO, device, socket, folder: refused unopened, its
    ``strerror`` naming what it is)."""
    path = Path(path)
    check_regular_file(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    fd = os.open(path, flags)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # swapped between the stat and the open
            raise _refused(path, st.st_mode)
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read()
    finally:
        os.close(fd)
