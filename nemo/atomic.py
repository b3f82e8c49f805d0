"""Atomic file writes and output folders: an interrupted or failed write leaves the previous file intact.

Every NEMO output goes through :func:`atomic_path`: the content is written to a temporary
name beside the target (same folder, so the final :func:`os.replace` is atomic on POSIX) and
only replaces the target once it is complete. A failure removes the temporary file.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def atomic_path(path: str | os.PathLike, keep_suffix: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``.

    Parameters
    ----------
    path : path-like
        The file to write; its folder must exist.
    keep_suffix : bool
        Keep ``path``'s suffix on the temporary name (for writers that choose the format
        from the suffix, e.g. matplotlib's ``savefig``).

    Yields
    ------
    Path
        Where to write. If the ``with`` block raises, the temporary file is removed and
        ``path`` is left as it was.
    """
    path = Path(path)
    stem, suffix = (path.stem, path.suffix) if keep_suffix else (path.name, "")
    tmp = path.with_name(f".{stem}.tmp{os.getpid()}{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # gone after a successful replace


def make_folder(folder: str | os.PathLike) -> Path:
    """Create an output ``folder`` (and its parents) or raise :class:`NemoError` saying why not.

    A file in the way, a refused ``mkdir`` (read-only file system, permissions) or a folder that
    is not writable each get a message naming the folder and the fix.
    """
    from nemo.errors import NemoError

    folder = Path(folder)
    blocker = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise NemoError(f"cannot create the folder {folder}: {blocker} is a file; choose another output path")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NemoError(f"cannot create the folder {folder} ({exc.strerror}); choose a writable output path") \
            from None
    if not os.access(folder, os.W_OK):
        raise NemoError(f"the folder {folder} is not writable; choose a writable output path")
    try:  # root passes os.access on /proc or a read-only mount: try a file, before any work is done
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as exc:
        raise NemoError(f"cannot write in the folder {folder} ({exc.strerror}); choose a writable output path") \
            from None
    return folder


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_json(
    path: str | os.PathLike, obj: Any, default: Callable[[Any], Any] | None = None, indent: int = 2
) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (``default`` serialises numpy values)."""
    write_text(path, json.dumps(obj, indent=indent, default=default or json_default, ensure_ascii=False) + "\n")


def json_default(obj: Any) -> Any:
    """JSON for numpy scalars and arrays and paths; anything else as its string."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return str(obj)
