"""Atomic file writes: no half-written file ever appears under its final name."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    The temporary name keeps the final suffix (writers such as meshio choose the format
    from it) and starts with a dot, so globbing for finished outputs never sees it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def writable_folder(path: str | Path) -> Path:
    """Check, before any long work whose results would otherwise be lost, that the folder
    ``path`` can be written or created; nothing is created here.

    Raises
    ------
    PermissionError
        The folder, or the nearest existing folder above it, is not a writable folder (or is
        a file); the message names it.
    """
    path = Path(path).absolute()
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(
            f"{existing}: cannot write output files there"
            + (f" (for {path})" if existing != path else "")
            + (": it is a file" if not existing.is_dir() else ": no write permission")
        )
    return path


def write_json(data: object, path: str | Path) -> Path:
    """Write ``data`` as indented JSON to ``path``, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2))
    return path
