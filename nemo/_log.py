"""Logging and progress output shared by the library and the CLI."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import TypeVar

logger = logging.getLogger("nemo")
T = TypeVar("T")


class _StderrHandler(logging.StreamHandler):
    """A handler that writes to whatever ``sys.stderr`` is now (not the one at set-up), so that
    a redirected or captured stderr (pytest, notebooks) never leaves it writing to a closed file."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler assigns it; the property always wins
        pass


def configure(verbosity: int = 0) -> None:
    """Send NEMO's log to stderr: 0 = warnings + progress, 1 = info, 2 = debug."""
    level = logging.INFO if verbosity <= 1 else logging.DEBUG
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("nemo: %(message)s"))
    logger.handlers[:] = [handler]
    logger.setLevel(level)
    logger.propagate = False


def pretty_unit(unit: str | None) -> str:
    """A length unit as printed and written: µm for its spellings (um, µm, μm, micron), "" for None."""
    return "" if unit is None else "µm" if unit in ("um", "µm", "μm", "micron") else unit


def listed(items: Iterable[str], most: int = 10, sep: str = "; ") -> str:
    """The first ``most`` of ``items`` joined by ``sep``, and how many more: a message about
    hundreds of objects (a tissue's nuclei) stays one readable line."""
    items = list(items)
    more = len(items) - most
    return sep.join(items[:most]) + (f"{sep}… and {more} more" if more > 0 else "")


#: Most objects whose steps log their own progress lines (more: the debug log, ``-vv``).
OBJECTS_LOGGED = 3


@contextmanager
def quiet_objects(n_objects: int, what: str) -> Iterator[None]:
    """A step's loop over ``n_objects`` objects: with more than :data:`OBJECTS_LOGGED` (a tissue's
    nuclei), each object's progress lines are left out unless the log shows debug lines (``-vv``),
    and one line says so; warnings still show."""
    if n_objects <= OBJECTS_LOGGED or logger.getEffectiveLevel() <= logging.DEBUG:
        yield
        return
    logger.info("%s: %d objects, each on its own (their progress: -vv)", what, n_objects)
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


@contextmanager
def step(message: str) -> Iterator[None]:
    """Log the start and the duration of a long step."""
    logger.info("%s ...", message)
    start = time.perf_counter()
    yield
    logger.info("%s done in %.2f s", message, time.perf_counter() - start)


def progress(items: Iterable[T], total: int | None = None, desc: str = "") -> Iterable[T]:
    """Wrap a chunked loop with a progress bar on stderr when logging at INFO or below."""
    if logger.isEnabledFor(logging.INFO) and sys.stderr.isatty():
        from tqdm import tqdm  # tqdm ships with snakemake; progress bars only on a terminal

        return tqdm(items, total=total, desc=f"nemo: {desc}", leave=False)
    return items
