"""Benchmark ``nemo mesh`` on the paper-scale vesicle (450³ voxels, R = 200 µm, 1 µm voxels).

Target (issue 2): ≤ 8 s wall time on 2 cores for the whole command (read, blur, threshold,
marching cubes at step 2, smoothing, split, three PLY files, sphere fit).

The input is the default synthetic vesicle from :mod:`nemo.synthetic` (``write_vesicle``)
when that module exists; otherwise an analytic stand-in of the same size: a 6 µm shell of
constant background just outside a sphere of radius 200 µm with random bright "fibre" voxels,
blurred (σ = 1 µm), uint8. It is written once into ``benchmarks/out/`` (git-ignored) and
reused; ``--fresh`` rewrites it.

Usage::

    python benchmarks/bench_mesh.py [--repeat 3] [--fresh] [--keep]

Prints the wall time of each run of ``nemo mesh`` (a fresh process each time, including
Python start-up and imports), its peak resident memory, and the inner sphere's radius error.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"
N = 450
R = 200.0


def analytic_vesicle(path: Path, seed: int = 0) -> dict:
    """Write a 450³ uint8 shell (inner radius R) with fibre-like speckle, plane by plane."""
    from scipy import ndimage as ndi

    from nemo.io import write_hyperstack

    rng = np.random.default_rng(seed)
    c = (N - 1) / 2.0
    yy, xx = np.mgrid[:N, :N].astype(np.float32) - c
    rho2 = yy**2 + xx**2
    vol = np.empty((N, N, N), dtype=np.float32)
    for z in range(N):
        r = np.sqrt(rho2 + (z - c) ** 2)
        shell = (r >= R) & (r < R + 6.0)
        plane = np.where(shell, 0.3, 0.0).astype(np.float32)
        fib = shell & (rng.random(shell.shape) < 0.15)
        plane[fib] = 1.0
        vol[z] = plane
    ndi.gaussian_filter(vol, 1.0, output=vol)
    data = np.clip(vol * 255.0, 0, 255).astype(np.uint8)
    write_hyperstack(path, data, (1.0, 1.0, 1.0), axes="ZYX")
    return {"radius": R, "centre": [c, c, c], "source": "analytic shell"}


def vesicle(fresh: bool) -> tuple[Path, dict]:
    OUT.mkdir(parents=True, exist_ok=True)
    try:
        from nemo.synthetic import write_vesicle
        have_synth = True
    except ImportError:
        have_synth = False
    path = OUT / ("vesicle_default.tif" if have_synth else "vesicle_analytic.tif")
    meta = path.with_suffix(".bench.json")
    if path.exists() and meta.exists() and not fresh:
        return path, json.loads(meta.read_text())
    t0 = time.perf_counter()
    if have_synth:
        from nemo.synthetic import write_vesicle

        write_vesicle(path)
        truth = json.loads(path.with_name(path.stem + ".truth.json").read_text())
        info = {"radius": truth["radius"], "centre": truth["centre"], "source": "nemo.synthetic default"}
    else:
        info = analytic_vesicle(path)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - t0:.1f} s")
    meta.write_text(json.dumps(info))
    return path, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--fresh", action="store_true", help="rewrite the input vesicle")
    ap.add_argument("--keep", action="store_true", help="keep the output meshes")
    ap.add_argument("extra", nargs="*", help="extra options for nemo mesh (after --)")
    args = ap.parse_args()
    image, truth = vesicle(args.fresh)
    mesh = OUT / "bench_mesh.ply"
    cmd = [sys.executable, "-m", "nemo", "mesh", str(image), "-o", str(mesh), "--split", "centre",
           "--fit-sphere", *args.extra]
    print("command:", " ".join(cmd[2:]).replace("nemo mesh", "nemo mesh", 1))
    print(f"input: {truth['source']}, cores available: {len(os.sched_getaffinity(0))}")
    times = []
    for i in range(args.repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        dt = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        peak = after.ru_maxrss
        cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        inside = next((line.split("done in ")[1] for line in proc.stdout.splitlines() if "done in" in line), "?")
        if proc.returncode:
            print(proc.stdout, proc.stderr)
            raise SystemExit(f"nemo mesh failed with exit {proc.returncode}")
        times.append(dt)
        print(f"run {i + 1}: {dt:.2f} s wall ({inside} after start-up and imports), {cpu:.2f} s CPU, "
              f"peak RSS {peak / 1024:.0f} MB" + ("" if peak > before.ru_maxrss else " (max over runs)"))
    spheres = json.loads(mesh.with_name(mesh.stem + ".sphere.json").read_text())
    inner = spheres["inner"]
    print(proc.stdout.strip())
    print(proc.stderr.strip())
    err = inner["radius"] - truth["radius"]
    centre_err = np.linalg.norm(np.subtract(inner["centre"], truth["centre"]))
    print(f"inner sphere radius {inner['radius']:.3f} (truth {truth['radius']}, error {err:+.3f} µm), "
          f"centre error {centre_err:.3f} µm, rms residual {inner['rms_residual']:.3f} µm")
    print(f"nemo mesh 450^3: best {min(times):.2f} s, median {np.median(times):.2f} s (target <= 8 s); "
          f"load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if not args.keep:
        for p in OUT.glob("bench_mesh*"):
            p.unlink()


if __name__ == "__main__":
    main()
