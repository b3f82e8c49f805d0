"""Shared test helpers."""

from __future__ import annotations

import numpy as np
import pytest

from nemo.cli import main as nemo_main


@pytest.fixture
def run_cli(capsys):
    """Run ``nemo ARGS...`` in-process; return (exit code, stdout, stderr)."""

    def _run(*args: str):
        code = nemo_main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return _run


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def wide_scale():
    """Director options for the paper's integration over half the patch (pixel ½ edge, at least
    r/20; σ = r/2): the most precise angles on clean stripes. The defaults (¼ edge, σ = 4 px,
    about one edge) trade a little of that precision for sharper defect cores."""
    from nemo.mesh import mean_edge_length

    def scale(mesh, radius: float) -> dict:
        pixel = max(0.5 * mean_edge_length(mesh), radius / 20)
        return {"pixel": pixel, "sigma": radius / pixel / 2}

    return scale
