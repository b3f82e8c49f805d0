"""Benchmark: scaling of the Snakemake workflow over the frames of a time-lapse.

Generates a synthetic time-lapse (default 20 frames) once, then runs the whole workflow on it
with ``--cores 1`` and with ``--cores 2`` (results cleared in between; the input is not timed)
and prints both wall times and their ratio. Every rule is single-threaded, so with N cores
N frames run in parallel and the ideal ratio is ~2.

    .venv/bin/python benchmarks/bench_workflow.py [--frames 20] [--radius 60] [--cores 1 2]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--radius", type=float, default=60.0, help="vesicle radius (µm)")
    ap.add_argument("--spacing", type=float, default=2.0, help="voxel size (µm)")
    ap.add_argument("--cores", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--workdir", help="keep the runs here (default: a temporary folder)")
    args = ap.parse_args()

    work = Path(args.workdir or tempfile.mkdtemp(prefix="nemo-bench-wf-"))
    work.mkdir(parents=True, exist_ok=True)
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    synth = cfg["datasets"]["demo"]["synthetic"]
    synth.update(frames=args.frames, radius=args.radius, spacing=[args.spacing] * 3)
    # length scales follow the smaller vesicle
    scale = args.radius / 100.0
    cfg["curvature"]["radius"] = round(12 * scale, 1)
    cfg["directors"].update(patch_radius=round(12 * scale, 1), n_patches=int(3000 * scale**2))
    cfg["order"]["radius"] = round(25 * scale, 1)
    cfg["defects"].update(min_distance=round(30 * scale, 1), contour_radius=round(20 * scale, 1))
    config = work / "bench.yaml"
    config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    smk = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work),
           "--configfile", str(config), "--quiet", "all"]

    subprocess.run([*smk, "--cores", "2", "resources/demo/vesicle.tif"], check=True)  # input, untimed
    n_jobs = None
    times = {}
    for cores in args.cores:
        shutil.rmtree(work / "results", ignore_errors=True)
        start = time.perf_counter()
        subprocess.run([*smk, "--cores", str(cores)], check=True)
        times[cores] = time.perf_counter() - start
        n_jobs = sum(1 for _ in (work / "results" / "demo" / "benchmarks").rglob("*.tsv"))
        print(f"--cores {cores}: {times[cores]:.1f} s wall ({n_jobs} jobs, {args.frames} frames)", flush=True)
    if 1 in times and 2 in times:
        print(f"ratio cores1 / cores2 = {times[1] / times[2]:.2f} (ideal 2.0)")
    print(f"work folder: {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
