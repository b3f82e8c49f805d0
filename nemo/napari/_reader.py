"""npe2 reader: open a NEMO results folder (frame, dataset or results root) in napari."""

from __future__ import annotations

from pathlib import Path

from nemo.errors import NemoError


def _one_path(path) -> str | None:
    if isinstance(path, (list, tuple)):
        return str(path[0]) if len(path) == 1 else None
    return str(path)


def get_reader(path):
    """Return :func:`read_results` when ``path`` is a NEMO results folder, else None."""
    p = _one_path(path)
    if p is None or not Path(p).is_dir():
        return None
    from nemo.layout import find_frames

    try:
        find_frames(p)
    except (NemoError, OSError):
        return None
    return read_results


def read_results(path) -> list[tuple]:
    """Layer data tuples of a results folder (all time points of the first channel)."""
    from nemo.napari.layers import layer_data

    return layer_data(_one_path(path))
