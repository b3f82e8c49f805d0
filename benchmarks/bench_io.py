"""Benchmark lazy reading of one (t, c) stack from a >= 4 GB TZCYX hyperstack.

Target (issue 2): ``nemo.io.read_stack`` returns one (Z, Y, X) stack in <= 1 s with peak
memory <= 1.5 x the stack's bytes.

The file (default 8 x 64 x 4 x 1024 x 1024 uint16 = 4.3 GB, uncompressed ImageJ hyperstack) is
written plane by plane through ``tifffile.memmap`` so it never sits in memory whole, into
``benchmarks/out/`` (git-ignored), and deleted afterwards unless ``--keep``.

Each read runs in a fresh Python process (imports done before timing) that reports wall time,
the peak of traced allocations (``tracemalloc``; numpy reports its buffers there) and the
peak resident set after the read (``VmHWM``) minus the resident set just before it (an
upper bound of the read's own peak: the import peak may be higher). Reads are done twice: with
the file evicted from the page cache (``posix_fadvise(DONTNEED)``, i.e. from disk) and warm.

Usage::

    python benchmarks/bench_io.py [--shape T Z C Y X] [--keep] [--reuse]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"

_CHILD = r"""
import json, os, sys, time, tracemalloc
import numpy as np
from nemo.io import read_stack
path, t, c, cold = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
if cold:
    fd = os.open(path, os.O_RDONLY)
    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    os.close(fd)
def _status(key):  # kB values of /proc/self/status (VmHWM is per process image, unlike ru_maxrss
    with open("/proc/self/status") as fh:  # which survives fork + exec from a big parent)
        return next(int(l.split()[1]) * 1024 for l in fh if l.startswith(key + ":"))
rss0 = _status("VmRSS")
tracemalloc.start()
t0 = time.perf_counter()
stack, info = read_stack(path, t, c)
dt = time.perf_counter() - t0
_, peak = tracemalloc.get_traced_memory()
tracemalloc.stop()
rss1 = _status("VmHWM")
print(json.dumps({"seconds": dt, "traced_peak": peak, "rss_growth": rss1 - rss0, "nbytes": stack.nbytes,
                  "shape": list(stack.shape), "checksum": float(stack[::7, ::13, ::17].astype(np.float64).sum())}))
"""


def plane_value(t: int, z: int, c: int, y: int, x: int) -> np.ndarray:
    """Deterministic content so a read can be checked without keeping the file in memory."""
    return ((np.arange(y)[:, None] * 7 + np.arange(x)[None, :] * 3 + t * 1000 + z * 50 + c * 10007) % 65521).astype(np.uint16)


def write_big(path: Path, shape: tuple[int, int, int, int, int], spacing=(2.0, 0.5, 0.5)) -> float:
    import tifffile

    T, Z, C, Y, X = shape
    t0 = time.perf_counter()
    mm = tifffile.memmap(path, shape=shape, dtype=np.uint16, imagej=True,
                         resolution=(1 / spacing[2], 1 / spacing[1]),
                         metadata={"axes": "TZCYX", "spacing": spacing[0], "unit": "micron"})
    base = plane_value(0, 0, 0, Y, X)
    for t in range(T):
        for z in range(Z):
            for c in range(C):
                mm[t, z, c] = (base + (t * 1000 + z * 50 + c * 10007)) % 65521  # same as plane_value
        mm.flush()
    del mm
    return time.perf_counter() - t0


def read_in_child(path: Path, t: int, c: int, cold: bool) -> dict:
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(path), str(t), str(c), "1" if cold else "0"],
                          capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(proc.stderr)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shape", type=int, nargs=5, default=(8, 64, 4, 1024, 1024), metavar=("T", "Z", "C", "Y", "X"))
    ap.add_argument("--keep", action="store_true", help="keep the file")
    ap.add_argument("--reuse", action="store_true", help="reuse an existing file of the same name")
    args = ap.parse_args()
    T, Z, C, Y, X = args.shape
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"big_{T}x{Z}x{C}x{Y}x{X}.tif"
    if not (args.reuse and path.exists()):
        dt = write_big(path, tuple(args.shape))
        print(f"wrote {path.name}: {path.stat().st_size / 1e9:.2f} GB in {dt:.1f} s")
    size = path.stat().st_size
    stack_bytes = Z * Y * X * 2
    print(f"file {size / 1e9:.2f} GB (TZCYX {T}x{Z}x{C}x{Y}x{X} uint16), one stack {stack_bytes / 1e6:.0f} MB")
    try:
        rng = np.random.default_rng(0)
        frames = [(T - 1, C - 1), (int(rng.integers(T)), int(rng.integers(C))), (0, 0)]
        for cold in (True, False):
            for t, c in frames:
                r = read_in_child(path, t, c, cold)
                # checksum of the expected content, computed plane by plane
                expect = sum(float(plane_value(t, z, c, Y, X)[::13, ::17].astype(np.float64).sum())
                             for z in range(0, Z, 7))
                ok = abs(r["checksum"] - expect) < 1e-6 * max(1.0, expect)
                print(f"{'cold' if cold else 'warm'} read t={t} c={c}: {r['seconds']:.3f} s, "
                      f"traced peak {r['traced_peak'] / stack_bytes:.2f} x stack, "
                      f"RSS growth {r['rss_growth'] / stack_bytes:.2f} x stack, content {'ok' if ok else 'WRONG'}")
    finally:
        if not args.keep:
            path.unlink()
            print(f"deleted {path.name}")


if __name__ == "__main__":
    main()
