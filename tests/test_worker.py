"""The warm worker (nemo.worker): same results, exit codes and streams as a fresh process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from nemo import worker
from nemo.io import write_hyperstack

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def warm(tmp_path_factory):
    """A worker owned by this test process (it stops when pytest ends)."""
    path = worker.start(idle_timeout=300)
    assert os.path.exists(path)
    return path


def nemo(args, cwd, socket_path, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT), **{worker.ENV: socket_path})
    return subprocess.run([sys.executable, "-m", "nemo", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300, **kw)


def test_a_command_in_the_worker_equals_a_fresh_process(warm, tmp_path):
    z, y, x = np.mgrid[:30, :30, :30]
    ball = ((np.sqrt((z - 15) ** 2 + (y - 15) ** 2 + (x - 15) ** 2) < 9) * 200).astype(np.uint8)
    write_hyperstack(tmp_path / "b.tif", ball, (1, 1, 1), axes="ZYX")
    for where, sock in (("w", warm), ("f", "off")):
        r = nemo(["mesh", "b.tif", "-o", f"{where}.ply", "--split", "none"], tmp_path, sock)
        assert r.returncode == 0, r.stderr
        assert "done in" in r.stdout  # stdout reaches the caller
        r = nemo(["curvature", f"{where}.ply", "-o", f"{where}.parquet"], tmp_path, sock)
        assert r.returncode == 0, r.stderr
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "w.parquet"), pd.read_parquet(tmp_path / "f.parquet"))
    assert (tmp_path / "w.ply").read_bytes() == (tmp_path / "f.ply").read_bytes()
    # errors: the same exit status and one-line message on the caller's stderr
    for sock in (warm, "off"):
        r = nemo(["curvature", "missing.ply", "-o", "x.parquet"], tmp_path, sock)
        assert r.returncode == 2 and "nemo curvature: error" in r.stderr and "Traceback" not in r.stderr
        r = nemo(["order", "--bogus"], tmp_path, sock)
        assert r.returncode == 2 and "usage" in r.stderr


def test_killing_the_caller_stops_the_command(warm, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), **{worker.ENV: warm})
    proc = subprocess.Popen([sys.executable, "-m", "nemo", "synth", "big.tif", "--radius", "200"], cwd=tmp_path,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(1.0)  # the whole synth takes ~4 s on 2 cores
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=30)
    assert proc.returncode != 0
    time.sleep(15)  # a surviving child would have written it by now
    assert not (tmp_path / "big.tif").exists()


def test_the_worker_stops_with_its_parent(tmp_path):
    code = "import sys; from nemo.worker import start; print(start(600))"
    path = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, PYTHONPATH=str(ROOT)),
                          capture_output=True, text=True, timeout=120).stdout.strip()
    for _ in range(100):
        if not os.path.exists(path):
            break
        time.sleep(0.1)
    assert not os.path.exists(path)
    # a stale socket path is ignored: the command runs in the caller
    r = nemo(["info", "--help"], tmp_path, path)
    assert r.returncode == 0


def test_a_worker_never_runs_changed_code(tmp_path):
    """After NEMO's sources change, the worker refuses (and stops): the caller runs the new code."""
    path = worker.start(idle_timeout=120)
    source = Path(worker.__file__).parent / "layout.py"
    before = os.stat(source)
    try:
        os.utime(source, (before.st_atime, before.st_mtime + 5))
        r = nemo(["info", "--help"], tmp_path, path)
        assert r.returncode == 0 and "usage" in r.stdout
        for _ in range(100):
            if not os.path.exists(path):
                break
            time.sleep(0.05)
        assert not os.path.exists(path)
    finally:
        os.utime(source, (before.st_atime, before.st_mtime))


def test_stop_ends_the_worker(tmp_path):
    path = worker.start(idle_timeout=120)
    worker.stop(path)
    time.sleep(3)  # the worker checks its folder every 2 s
    r = nemo(["info", "--help"], tmp_path, path)
    assert r.returncode == 0 and not os.path.exists(os.path.dirname(path))
    alive = subprocess.run(["pgrep", "-f", path], capture_output=True, text=True).stdout.split()
    assert not alive, alive  # the worker process is gone
