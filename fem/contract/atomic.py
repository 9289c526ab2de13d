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
    """Create the folder ``path`` if needed and check that files can be written there, before
    any long work whose results would otherwise be lost.

    Raises
    ------
    PermissionError
        The folder cannot be created or written; the message names it.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with atomic_path(path / ".write-test") as tmp:
            tmp.write_bytes(b"")
        (path / ".write-test").unlink()
    except OSError as exc:
        raise PermissionError(f"{path}: cannot write output files there ({exc})") from exc
    return path


def write_json(data: object, path: str | Path) -> Path:
    """Write ``data`` as indented JSON to ``path``, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2))
    return path
