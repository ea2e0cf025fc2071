"""Atomic writes: a file or a folder appears complete, or not at all.

Every writer of graphcal goes through these functions, so an interrupted run (Ctrl-C, a full disk,
an exception half-way through a dataset) never leaves a half-written file or folder behind, and
never damages what was there before:

* :func:`atomic_write_text` / :func:`atomic_write_bytes` write into a temporary file in the same
  folder, ``fsync`` it, then ``os.replace`` it onto the target (atomic on POSIX and Windows). The
  temporary file is removed if anything fails.
* :func:`atomic_directory` lets the caller build a whole folder in a hidden sibling temporary
  folder, and renames it onto the final name only when the ``with`` block ends without an
  exception. An existing non-empty folder is never replaced unless ``overwrite=True``; on any
  exception the temporary folder is removed and the final path is left exactly as it was. A
  previous folder is swapped out in one system call where the OS has one (Linux
  ``renameat2(RENAME_EXCHANGE)``), with Ctrl-C held back until the swap is over. A process killed
  outright (SIGKILL, power loss) can leave its hidden sibling folders behind; they carry its process
  id, and the next :func:`atomic_directory` on the same folder removes those of processes that are
  gone (a previous folder moved aside and never replaced is put back instead).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import Callable, Iterable, Iterator

from graphcal.errors import GraphcalError

__all__ = ["OutputExistsError", "InterruptedAfterWrite", "atomic_file", "atomic_write_text", "atomic_write_bytes", "atomic_directory",
           "fsync_directory", "check_output_folder", "check_command_output", "previous_output_files",
           "Terminated", "sigterm_as_interrupt", "output_lock", "check_output_outside"]


class OutputExistsError(GraphcalError, FileExistsError):
    """The output path already holds something we must not replace (pass ``overwrite=True``)."""


class OutputLocationError(GraphcalError):
    """An output cannot be written where it was asked for (its parent is a file, or not writable)."""


class OutputWriteError(OutputLocationError, OSError):
    """Writing an output failed part-way (the disk is full, a quota or file-size limit, a read-only
    or failing file system): nothing was written, and what was there before is unchanged. Still an
    OSError for callers that catch those; the command line prints it as one line (a GraphcalError).
    ``reason``: the system's words (``"No space left on device"``)."""

    def __init__(self, message: str, reason: str = ""):
        super().__init__(message)
        self.reason = reason


#: the errors of a write that ran out of room or of a file system that failed: reported as one line
#: naming the output (OutputWriteError), not as a traceback
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO}


def _write_error(path: Path, exc: OSError, what: str = "file") -> OutputWriteError:
    if isinstance(exc, OutputWriteError):
        reason = exc.reason
    else:
        reason = exc.strerror or str(exc) or type(exc).__name__
    return OutputWriteError(f"{path}: cannot write this output {what}: {reason} (nothing was written; "
                            f"what was there before is unchanged)", reason)


def _location_error(path: Path, exc: OSError, folder: Path | None = None) -> OutputLocationError:
    """The error for an output ``path`` that could not be created in ``folder`` (default: its parent)."""
    return OutputLocationError(f"{path}: cannot write in {folder or path.parent}: {exc.strerror or exc}")


def make_parent_folder(path: str | Path) -> None:
    """Create the folder of the output ``path`` (and its parents); :class:`OutputLocationError`
    naming ``path`` when that cannot be done (a parent is a file, no permission)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _location_error(path, exc) from None


def check_output_location(path: str | Path) -> None:
    """Refuse early, before any work, an output ``path`` that cannot be written: the nearest existing
    folder above it must be a folder in which a (hidden, at once removed) folder can be created.
    Raises :class:`OutputLocationError` naming ``path``."""
    path = Path(path).absolute()
    base = path.parent
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise OutputLocationError(f"{path}: cannot write there: {base} is a file, not a folder")
    try:
        probe = tempfile.mkdtemp(prefix=".graphcal-write-check-", dir=str(base))
    except OSError as exc:
        raise _location_error(path, exc, base) from None
    os.rmdir(probe)


_UMASK_LOCK = threading.Lock()


def _current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux), else briefly set."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def fsync_directory(path: str | Path) -> None:
    """Flush a folder's entries (the result of a rename) to disk; best effort (no-op on Windows)."""
    try:
        fd = os.open(str(path), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _temp_sibling(path: Path, suffix: str = ".tmp") -> tuple[int, Path]:
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=str(path.parent))
    except OSError as exc:
        raise _location_error(path, exc) from None
    return fd, Path(name)


@contextlib.contextmanager
def atomic_file(path: str | Path, *, overwrite: bool = True, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends without an exception, flush it to
    disk and rename it onto ``path``; otherwise remove it and leave ``path`` unchanged.

    For writers that need a file name (Open3D, ``numpy.save``): write the whole file to the yielded
    path inside the ``with`` block. ``suffix`` lets such writers see the right extension (".ply").
    The result gets the permissions of the file it replaces, or ``0o666`` minus the umask.

    Raises:
        OutputExistsError: ``overwrite`` is False and ``path`` exists (checked before and at the end).
    """
    path = Path(path)
    if not overwrite and (path.exists() or path.is_symlink()):
        raise OutputExistsError(f"{path}: already exists; refusing to replace it (overwrite=False)")
    try:
        mode = path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~_current_umask()
    except OSError:
        mode = 0o666 & ~_current_umask()
    fd, tmp = _temp_sibling(path, suffix)
    os.close(fd)
    try:
        yield tmp
        fd = os.open(str(tmp), os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, mode)
        if not overwrite and (path.exists() or path.is_symlink()):
            raise OutputExistsError(f"{path}: already exists; refusing to replace it (overwrite=False)")
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, GraphcalError):
            # a full disk, a quota, a failing file system, or a writer (Open3D) that gave up
            raise _write_error(path, exc) from None
        raise
    fsync_directory(path.parent)


def atomic_write_bytes(path: str | Path, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, ``os.replace``).

    Args:
        path: target file. Its folder must exist.
        data: the complete file content.
        overwrite: if False, refuse (:class:`OutputExistsError`) when ``path`` already exists.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    The new file gets the permissions of the file it replaces, or ``0o666`` minus the umask.
    On any failure the temporary file is removed and ``path`` is unchanged.
    """
    with atomic_file(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str, *, overwrite: bool = True, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (UTF-8, newlines written as given); see :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, text.encode(encoding), overwrite=overwrite)


def _is_empty_dir(path: Path) -> bool:
    with os.scandir(path) as it:
        return next(it, None) is None


def _check_target(final: Path, overwrite: bool) -> None:
    if final.is_symlink():
        raise OutputExistsError(f"{final}: is a symbolic link; refusing to replace it")
    if final.exists():
        if not final.is_dir():
            raise OutputExistsError(f"{final}: exists and is not a folder; refusing to replace it")
        if not overwrite and not _is_empty_dir(final):
            raise OutputExistsError(
                f"{final}: folder exists and is not empty; refusing to replace it (choose another "
                f"output folder, or ask for overwrite)"
            )


@contextlib.contextmanager
def atomic_directory(final_dir: str | Path, *, overwrite: bool = False) -> Iterator[Path]:
    """Build a folder atomically: ``with atomic_directory(out) as tmp:`` write into ``tmp``.

    ``tmp`` is a hidden sibling of ``final_dir`` (same file system, so the final rename is atomic).
    When the block ends normally, ``tmp`` is renamed to ``final_dir``:

    * ``final_dir`` absent or an empty folder: it simply appears, complete.
    * ``final_dir`` a non-empty folder: refused with :class:`OutputExistsError` (checked before the
      block runs and again at the end) unless ``overwrite=True``; then the two folders are exchanged
      in one system call where the OS has one (Linux), else the old folder is moved aside and the new
      one renamed in (if that fails, the old folder is put back); only then is the old one deleted.
    * ``final_dir`` a file or a symbolic link: always refused.

    If the block raises, ``tmp`` is deleted and ``final_dir`` is untouched. A Ctrl-C (SIGINT) that
    arrives during the swap is held back until it is over and then raised as
    :class:`InterruptedAfterWrite` (the new folder is in place). Hidden siblings left by a process
    that was killed (``.NAME.tmp-PID-*``, ``.NAME.old-PID-*``) are cleaned up first
    (:func:`_clean_stale_siblings`). The parent folder is created if needed. The finished folder
    gets ``0o777`` minus the umask as permissions.
    """
    final = Path(final_dir)
    if final.name in ("", ".", ".."):
        final = final.resolve()
    make_parent_folder(final)
    _clean_stale_siblings(final)
    _check_target(final, overwrite)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-{os.getpid()}-", dir=str(final.parent)))
    except OSError as exc:
        raise _location_error(final, exc) from None
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_current_umask())
        with _sigint_held() as held:
            _commit_directory(tmp, final, overwrite)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OutputWriteError) or (
            isinstance(exc, OSError) and not isinstance(exc, GraphcalError) and exc.errno in _WRITE_ERRNOS
        ):  # a file of the folder could not be written (named inside the hidden folder): name the folder
            raise _write_error(final, exc, "folder") from None
        raise
    fsync_directory(final.parent)
    if held:
        raise InterruptedAfterWrite(final)


class InterruptedAfterWrite(KeyboardInterrupt):
    """Ctrl-C arrived while a finished output folder was being put in place: the folder is complete."""

    def __init__(self, path: Path):
        super().__init__(f"after {path} was written (complete)")
        self.path = path


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived while a command ran (raised by :func:`sigterm_as_interrupt`): the command stops
    as on Ctrl-C, its hidden temporary folder removed, nothing half-written left behind."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated("terminated (SIGTERM)")


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """During the block SIGTERM raises :class:`Terminated` (a KeyboardInterrupt), so ``finally``
    blocks and :func:`atomic_directory`'s clean-up run, instead of the process dying where it stands
    and leaving its hidden ``.NAME.tmp-PID-*`` folder beside the output. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _sigint_held() -> Iterator[list]:
    """Hold back SIGINT (and SIGTERM, where a Python handler is installed) during the block (main
    thread only: Python runs signal handlers there, and only there can they be changed); yields a list
    that is non-empty if one arrived."""
    held: list = []
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(sig)
        if callable(handler):  # not ignored, default or a handler installed outside Python
            previous[sig] = signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield held
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def check_output_outside(out_dir: str | Path, input_dir: str | Path, *, what: str = "the dataset") -> None:
    """Refuse an output folder that is the input folder or lies inside it: a command never writes
    into what it reads (``--out DATASET/results`` would add files to the dataset)."""
    out, src = Path(out_dir).resolve(), Path(input_dir).resolve()
    if src.is_dir() and (out == src or src in out.parents):
        raise OutputLocationError(f"--out {out_dir} is inside {what} {input_dir}: graphcal does not write into "
                                  "its input; choose a folder outside it")


@contextlib.contextmanager
def output_lock(out_dir: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on the output ``out_dir`` for the block (``flock`` on a hidden
    ``.NAME.lock`` file beside it, released when the process ends, however it ends): a second command
    writing the same output is refused at once with a clear message instead of silently replacing
    the first one's result when both finish. Where the lock file cannot be made (the parent folder
    does not exist yet, or is not writable) the block runs unlocked and the command's own checks
    report the location."""
    import fcntl

    final = Path(out_dir)
    if final.name in ("", ".", ".."):
        final = final.resolve()
    lock_path = final.parent / f".{final.name}.lock"
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:  # no parent folder yet, or not writable: the command's own checks say so, by name
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputLocationError(f"{final} is being written by another graphcal command right now "
                                      "(it holds the lock): wait for it to finish or choose another --out") from None
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                os.unlink(lock_path)
    finally:
        os.close(fd)


_RENAME_EXCHANGE = 2  # linux/fs.h
_renameat2 = None


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one system call (Linux ``renameat2(RENAME_EXCHANGE)``); False where the OS,
    the C library or the file system has no such call (nothing was changed then)."""
    global _renameat2
    if _renameat2 is None:
        _renameat2 = False
        if os.name == "posix":
            import ctypes

            try:
                fn = ctypes.CDLL(None, use_errno=True).renameat2
            except (OSError, AttributeError):
                fn = None
            if fn is not None:
                fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
                fn.restype = ctypes.c_int
                _renameat2 = fn
    if not _renameat2:
        return False
    import ctypes

    at_fdcwd = -100  # AT_FDCWD: paths relative to the working folder (absolute ones as they are)
    if _renameat2(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False  # not supported here: the caller falls back to two renames
    raise OSError(err, os.strerror(err), str(b))


def _commit_directory(tmp: Path, final: Path, overwrite: bool) -> None:
    _check_target(final, overwrite)
    if not final.exists() or _is_empty_dir(final):
        try:
            os.rename(tmp, final)  # POSIX: atomically replaces an empty folder too
            return
        except OSError:
            if final.is_dir() and _is_empty_dir(final):  # e.g. Windows: no rename onto a folder
                os.rmdir(final)
                os.rename(tmp, final)
                return
            if not final.exists():
                raise
            _check_target(final, overwrite)  # something appeared meanwhile: refuse unless overwrite
    # overwrite=True and final is a non-empty folder
    if _exchange(tmp, final):  # one step: final is the new folder, tmp holds the old one
        shutil.rmtree(tmp, ignore_errors=True)
        return
    backup = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-{os.getpid()}-", dir=str(final.parent)))
    os.rmdir(backup)
    os.rename(final, backup)
    try:
        os.rename(tmp, final)
    except BaseException:
        with contextlib.suppress(OSError):
            os.rename(backup, final)
        raise
    shutil.rmtree(backup, ignore_errors=True)


def _process_gone(pid: int) -> bool:
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except (PermissionError, OSError):  # another user's process: alive
        return False
    return False


def _clean_stale_siblings(final: Path) -> None:
    """Remove the hidden siblings ``.NAME.tmp-PID-*`` / ``.NAME.old-PID-*`` of ``final`` whose
    process is gone (killed while writing). A ``.old`` folder is a previous output moved aside:
    when ``final`` is missing (killed between the two renames of the fallback swap) it is put back
    instead. Siblings of live processes, and anything else, are left alone."""
    pattern = re.compile(rf"^\.{re.escape(final.name)}\.(tmp|old)-(\d+)-[A-Za-z0-9_]+$")
    try:
        names = sorted(os.listdir(final.parent))
    except OSError:
        return
    for name in names:
        m = pattern.match(name)
        if m is None or not _process_gone(int(m.group(2))):
            continue
        path = final.parent / name
        if path.is_symlink() or not path.is_dir():
            continue
        if m.group(1) == "old" and not (final.exists() or final.is_symlink()):
            with contextlib.suppress(OSError):  # if that fails, it stays as it is: never deleted
                os.rename(path, final)  # the previous results, back where they were
            continue
        shutil.rmtree(path, ignore_errors=True)


def _shown(names: list[str]) -> str:
    return ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")


def check_output_folder(out_dir: str | Path, previous_files: Callable[[Path], Iterable[str] | None], *, what: str,
                        overwrite: bool = True) -> None:
    """The one policy of every graphcal command that writes an output folder: refuse
    (:class:`OutputExistsError`) unless ``out_dir`` is absent, an empty folder, or -- with
    ``overwrite`` -- a folder that holds a previous output of the same kind and nothing else.

    Args:
        out_dir: the output folder.
        previous_files: ``previous_files(folder)`` -> the names a previous output of this kind wrote
            there (e.g. :func:`previous_output_files`), or None when the folder holds no such output.
        what: the kind of output in messages, e.g. ``"graphcal calibration"``.
        overwrite: allow replacing a previous output of this kind.
    """
    out = Path(out_dir)
    if out.is_symlink():
        raise OutputExistsError(f"{out}: is a symbolic link; refusing to write a {what} there")
    if not out.exists():
        check_output_location(out)
        return
    if not out.is_dir():
        raise OutputExistsError(f"{out}: exists and is not a folder; refusing to write a {what} there")
    entries = sorted(os.listdir(out))
    if not entries:
        return
    if not overwrite:
        raise OutputExistsError(f"{out}: folder exists and is not empty; refusing to replace it (overwrite=False)")
    ours = previous_files(out)
    if ours is None:
        raise OutputExistsError(f"{out}: folder is not empty and holds no {what} ({_shown(entries)}); refusing to "
                                "replace it: choose an empty or new output folder")
    foreign = [e for e in entries if e not in set(ours)]
    if foreign:
        raise OutputExistsError(f"{out}: folder holds a previous {what} but also files graphcal did not write "
                                f"({_shown(foreign)}); refusing to replace it: move those files or choose another "
                                "output folder")


def check_command_output(out_dir: str | Path, manifest: str, files: Iterable[str], format_prefix: str, *, what: str,
                         overwrite: bool = True) -> None:
    """:func:`check_output_folder` for a command whose previous output is recognised by its manifest
    file ``manifest`` (``format`` starting with ``format_prefix``) and writes ``files`` (plus the
    manifest's ``output_files``); see :func:`previous_output_files`."""
    check_output_folder(out_dir, lambda f: previous_output_files(f, manifest, files, format_prefix), what=what,
                        overwrite=overwrite)


def previous_output_files(folder: Path, manifest: str, names: Iterable[str], format_prefix: str) -> set[str] | None:
    """The files a previous graphcal output wrote in ``folder``, from its manifest file (YAML or
    JSON, with ``format`` starting with ``format_prefix`` and optionally an ``output_files`` list):
    ``names`` plus the listed plain file names; None when there is no such manifest."""
    import json

    import yaml

    path = Path(folder) / manifest
    if not path.is_file() or path.is_symlink():
        return None
    try:
        text = path.read_text(encoding="utf-8")
        doc = json.loads(text) if manifest.endswith(".json") else yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, ValueError, TypeError, RecursionError, yaml.YAMLError):
        return None
    if not isinstance(doc, dict) or not str(doc.get("format", "")).startswith(format_prefix):
        return None
    out = set(names)
    listed = doc.get("output_files")
    if isinstance(listed, list):
        out |= {n for n in listed if isinstance(n, str) and n and "/" not in n and "\\" not in n and n not in (".", "..")}
    return out
