"""Paths written in a dataset's files: resolved inside the dataset folder, and shown relative to it."""

from __future__ import annotations

from pathlib import Path, PurePosixPath, PureWindowsPath

from graphcal.errors import DatasetError


def path_inside(root: Path, rel: str, file: Path | str, where: str, *, root_resolved: Path | None = None,
                resolved: Path | None = None) -> Path:
    """Resolve a relative path written in a dataset file; it must stay inside the dataset folder.
    ``rel``: the path as written (``/`` or ``\\``); ``file``, ``where``: the file and place that wrote
    it, for the message. Returns ``root / rel``; DatasetError for an absolute path or one leading out.
    ``root_resolved``, ``resolved``: ``root.resolve()`` and the path's own, when the caller has them
    (a resolve costs ~0.1 ms: a dataset's clouds are listed several times a calibration)."""
    rel_norm = rel.replace("\\", "/")
    if PurePosixPath(rel_norm).is_absolute() or PureWindowsPath(rel).is_absolute() or PureWindowsPath(rel).drive:
        raise DatasetError(file, where, "a path relative to the dataset folder", f"{rel} (absolute)")
    full = root / rel_norm
    try:
        resolved = full.resolve() if resolved is None else resolved
        inside = resolved.is_relative_to(root.resolve() if root_resolved is None else root_resolved)
    except (OSError, RuntimeError, ValueError):
        inside = False
    if not inside:
        raise DatasetError(file, where, "a path inside the dataset folder (no '..', no link leading out)", rel)
    return full


def resolved_or_none(path: Path) -> Path | None:
    """``path.resolve()``, or None where it fails (a link loop): :func:`path_inside` then reports it."""
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return None


def shown_path(root: Path, f: Path) -> str:
    """``f`` relative to the dataset folder ``root`` where it lies inside it, else in full."""
    try:
        return str(Path(f).relative_to(root))
    except ValueError:
        return str(f)
