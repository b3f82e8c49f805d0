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
