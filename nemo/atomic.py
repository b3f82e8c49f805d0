"""Atomic file writes: an interrupted or failed write leaves the previous file intact.

Every NEMO output goes through :func:`atomic_path`: the content is written to a temporary
name beside the target (same folder, so the final :func:`os.replace` is atomic on POSIX) and
only replaces the target once it is complete. A failure removes the temporary file.
"""

from __future__ import annotations

import json
import os
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
