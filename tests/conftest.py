"""Shared test helpers."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from nemo.cli import main as nemo_main

_NO_SLURM_SHIM: list[str] = []  # this process's shim folder, made once


def snakemake_env(slurm: bool = False) -> dict[str, str]:
    """The environment of the tests' Snakemake runs: warnings off and, unless ``slurm``, a ``scontrol``
    that fails at once first on the PATH. The SLURM executor plugin (a test dependency) asks
    ``scontrol show config`` for MinJobAge whenever Snakemake starts, and waits out its 10-s timeout
    where SLURM's client is installed but no controller runs (a machine after ``make test-slurm``):
    10 s per run, minutes per suite. The SLURM test itself (``slurm=True``) keeps the real one. The
    shim lives in a private folder of this process (``mkdtemp``: nobody else's files on the PATH)."""
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    if slurm:
        return env
    if not _NO_SLURM_SHIM:
        folder = Path(tempfile.mkdtemp(prefix="nemo-tests-no-slurm-"))
        (folder / "scontrol").write_text("#!/bin/sh\nexit 1\n")
        (folder / "scontrol").chmod(0o700)
        _NO_SLURM_SHIM.append(str(folder))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
    env["PATH"] = f"{_NO_SLURM_SHIM[0]}{os.pathsep}{env.get('PATH', '')}"
    return env


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


@pytest.fixture
def cli_error():
    """Check a failed ``nemo`` run: exit status 2 and, progress lines ("nemo: ...") aside, exactly
    one ``nemo CMD: error: ...`` line, no traceback, naming each of ``words`` (case-insensitive).
    Returns that line."""

    def check(code: int, err: str, *words: str) -> str:
        assert code == 2, err
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("nemo: ")]
        assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err, err
        for word in words:
            assert word.lower() in lines[0].lower(), (word, lines[0])
        return lines[0]

    return check


SHELL_N = 40  # the shell image is SHELL_N³ voxels of 1 µm
SHELL_R_IN, SHELL_R_OUT = 10.0, 14.0  # its wall, µm from SHELL_CENTRE
SHELL_CENTRE = (19.3, 19.6, 19.8)  # (x, y, z), off the voxel grid


def _shell_image() -> np.ndarray:
    z, y, x = (np.arange(SHELL_N, dtype=float),) * 3
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    cx, cy, cz = SHELL_CENTRE
    r = np.sqrt((xx - cx) ** 2 + (yy - cy) ** 2 + (zz - cz) ** 2)
    wall = 0.5 * (np.tanh((r - SHELL_R_IN) / 0.8) - np.tanh((r - SHELL_R_OUT) / 0.8))
    return (200 * wall).astype(np.uint8)


@pytest.fixture
def shell_image():
    """A smooth hollow shell SHELL_R_IN < r < SHELL_R_OUT in a SHELL_N³ ZYX grid of 1 µm voxels
    (uint8: 0 outside, 200 inside the wall); a fresh array each time, free to modify."""
    return _shell_image()


@pytest.fixture(scope="session")
def meshed_shell(tmp_path_factory):
    """A folder with ``shell.tif`` (:func:`shell_image`, 1 µm voxels, calibrated) and ``m.ply``,
    ``m.inner.ply``, ``m.outer.ply`` from ``nemo mesh --split centre --step 1``.

    Shared by the whole session: read it, write outputs to the test's own ``tmp_path``."""
    from nemo.io import write_hyperstack

    d = tmp_path_factory.mktemp("shell")
    write_hyperstack(d / "shell.tif", _shell_image(), (1.0, 1.0, 1.0), axes="ZYX")
    args = ["mesh", str(d / "shell.tif"), "-o", str(d / "m.ply"), "--split", "centre", "--step", "1"]
    assert nemo_main(args) == 0
    return d


@pytest.fixture(scope="session")
def write_two_vesicles():
    """:func:`_write_two_vesicles`, for tests of several objects."""
    return _write_two_vesicles


def _write_two_vesicles(path) -> list[dict]:
    """Two synthetic vesicles side by side in one stack (R = 30 and 22 µm, 1.5 µm voxels, the
    second's defects turned at random): the image for several-object tests.

    Returns each vesicle's truth in the joint image, largest first: ``centre`` (3,) and
    ``defects`` (4, 3), physical x, y, z.
    """
    from nemo.io import write_hyperstack
    from nemo.synthetic import vesicle

    sp = 1.5
    a, ta = vesicle(radius=30, spacing=(sp,) * 3, seed=1)
    b, tb = vesicle(radius=22, spacing=(sp,) * 3, rotate=5, seed=2)
    a, b = a[0, :, 0], b[0, :, 0]
    vol = np.zeros((a.shape[0], a.shape[1], a.shape[2] + b.shape[2]), a.dtype)
    vol[:, :, :a.shape[2]] = a
    vol[:b.shape[0], :b.shape[1], a.shape[2]:] = b
    write_hyperstack(path, vol[None, :, None], spacing=(sp,) * 3)
    offset = np.array([a.shape[2] * sp, 0.0, 0.0])
    return [{"centre": np.asarray(t["centre"]) + o,
             "defects": np.array([[q["x"], q["y"], q["z"]] for q in t["defects"]]) + o}
            for t, o in ((ta, np.zeros(3)), (tb, offset))]
