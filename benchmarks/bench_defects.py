"""Benchmark: defect localisation + charges, and the whole ``nemo run`` chain, on the paper's vesicle.

Generates the paper's synthetic vesicle (R = 200 µm, 1 µm voxels, 4 × +1/2 tetrahedral; or
uses --image), runs ``nemo run`` in a subprocess (wall time and peak memory of that process),
then times :func:`nemo.defects.find_defects` alone on its outputs and prints the localisation
errors and charges against the ground truth.

    python benchmarks/bench_defects.py                 # default vesicle in a temp folder
    python benchmarks/bench_defects.py --image v.tif   # an existing image with v.truth.json
    python benchmarks/bench_defects.py --rotate 3 --noise 20 --spacing 2 1 1

Targets (issue 5): localisation + charges <= 3 s; whole ``nemo run`` <= 20 s on 2 cores with
peak memory <= 3 GB; every defect within 2 µm of the truth, |charge - 1/2| <= 0.05.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--image", help="existing image (with IMAGE.truth.json); default: generate")
    ap.add_argument("--workdir", help="folder for the image and outputs (default: a temp folder)")
    ap.add_argument("--rotate", type=int, help="random rotation seed of the defect set")
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--spacing", type=float, nargs=3, default=(1.0, 1.0, 1.0))
    ap.add_argument("--preset", default="tetrahedron")
    ap.add_argument("--repeat", type=int, default=3, help="repeats of the find_defects timing")
    args = ap.parse_args()

    from nemo.defects import find_defects
    from nemo.mesh import load_mesh
    from nemo.synthetic import read_truth, write_vesicle
    from nemo.tables import read_table

    work = Path(args.workdir or tempfile.mkdtemp(prefix="nemo-bench-defects-"))
    work.mkdir(parents=True, exist_ok=True)
    image = Path(args.image) if args.image else work / "vesicle.tif"
    if not args.image:
        t0 = time.perf_counter()
        write_vesicle(image, spacing=tuple(args.spacing), defects=args.preset, rotate=args.rotate,
                      noise=args.noise)
        print(f"synthetic vesicle written in {time.perf_counter() - t0:.1f} s: {image}")
    truth = read_truth(image)
    out = work / "run"

    cmd = [sys.executable, "-m", "nemo", "run", str(image), "-o", str(out)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2
    if proc.returncode:
        print(proc.stderr)
        return proc.returncode
    print(proc.stdout.strip())

    import json

    import pandas as pd

    from nemo import layout

    summary = json.loads((out / "summary.json").read_text())
    layer = next(iter(summary["layers"]))  # the run's (first) layer
    info = summary["layers"][layer]
    mesh = load_mesh(out / f"mesh.{info['surface']}.ply")
    odf = read_table(out / layout.layer_file("order", layer), kind="order")
    ddf = read_table(out / layout.layer_file("directors", layer), kind="directors")
    if (out / layout.refined_file(layer)).exists():  # nemo run's refinement directors
        ddf = pd.concat([ddf, read_table(out / layout.refined_file(layer), kind="directors")], ignore_index=True)
    times = []
    for _ in range(args.repeat):  # the search alone, on all of the run's directors
        t0 = time.perf_counter()
        find_defects(mesh, odf, ddf, avg_radius=info["defects_parameters"]["avg_radius"])
        times.append(time.perf_counter() - t0)
    df = read_table(out / layout.layer_file("defects", layer), kind="defects")  # what the run reports
    _report(df, truth, mesh, ddf, {**summary, "euler_check": info["euler_check"]}, wall=wall, peak_gb=peak_gb,
            times=times)
    print(f"outputs in {work}")
    return 0


def _report(df, truth: dict, mesh, ddf, summary: dict, wall: float, peak_gb: float, times: list) -> None:
    """Print the run's timings and the defects' errors against the truth."""
    rec = [d for d in truth["defects"] if d["t"] == 0 and d["layer"] == 0]
    pos = np.array([[d["x"], d["y"], d["z"]] for d in rec])
    charges = np.array([d["charge"] for d in rec])
    d = np.linalg.norm(df[["x", "y", "z"]].to_numpy()[:, None] - pos[None], axis=2)
    k = d.argmin(axis=1) if len(df) else np.zeros(0, int)
    err = d.min(axis=1) if len(df) else np.zeros(0)
    found = len(set(k.tolist())) == len(pos) and len(df) == len(pos)
    cores = os.cpu_count()
    print()
    print(f"machine: {cores} cores; load average {os.getloadavg()[0]:.2f}")
    print(f"mesh: {len(mesh.vertices)} vertices; {len(ddf)} directors")
    print(f"nemo run (one frame): {wall:.2f} s wall, peak memory {peak_gb:.2f} GB   [target <= 20 s, <= 3 GB]")
    print("  stages (s): " + ", ".join(f"{k_}={v:.2f}" for k_, v in summary["timings_s"].items()))
    print(f"find_defects (localisation + charges): median {np.median(times):.2f} s of {len(times)}   [target <= 3 s]")
    print(f"defects: {len(df)} reported, {len(pos)} true; all found once: {found}")
    print(f"  localisation error (µm): {np.round(err, 2).tolist()}  max {err.max() if len(err) else float('nan'):.2f}"
          f"  mean {err.mean() if len(err) else float('nan'):.2f}   [target each <= 2, paper 3.58]")
    if len(df):
        dq = df["charge"].to_numpy() - charges[k]
        print(f"  charges: {np.round(df['charge'].to_numpy(), 3).tolist()}  max |charge - truth| {np.abs(dq).max():.3f}"
              "   [target <= 0.05]")
    chk = summary["euler_check"]
    print(f"  Euler check: sum {chk['sum_charge']:.3f} vs chi {chk['euler_characteristic']} -> "
          f"{'ok' if chk['matches'] else 'MISMATCH'}")


if __name__ == "__main__":
    raise SystemExit(main())
