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


def configure(verbosity: int = 0) -> None:
    """Send NEMO's log to stderr: 0 = warnings + progress, 1 = info, 2 = debug."""
    level = logging.INFO if verbosity <= 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("nemo: %(message)s"))
    logger.handlers[:] = [handler]
    logger.setLevel(level)
    logger.propagate = False


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
