"""Benchmark the figures (``nemo render``) and the napari layers on the paper-scale vesicle.

The frame is the ``nemo run`` output of the default synthetic vesicle (R = 200 µm, 1 µm
voxels, 450³; ``benchmarks/out/vesicle_default.tif``, written by ``nemo.synthetic`` when
missing) analysed with the paper's parameters into ``benchmarks/out/render_frame/`` (reused;
``--fresh`` recomputes).

Usage::

    python benchmarks/bench_render.py [--fresh] [--napari]

Prints: mesh size; wall time and peak memory of ``nemo render FRAME -o OUT`` (a fresh process,
all figures: 3 pyvista renders per layer + H/K + matplotlib figures) and of the matplotlib-only
run (``--no-surfaces``); ``layer_data`` (napari layer tuples, no napari import) time; with
``--napari`` also opening the viewer and taking a screenshot under ``xvfb-run``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"


def _timed(cmd: list[str]) -> tuple[float, float]:
    """Wall time (s) and peak RSS (MB) of one child process (via a fresh wrapper process)."""
    wrapper = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
               "subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL); "
               "print(time.perf_counter() - t, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", wrapper, *cmd], check=True, capture_output=True, text=True)
    wall, peak_kb = out.stdout.split()[-2:]
    return float(wall), float(peak_kb) / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fresh", action="store_true", help="recompute the frame results")
    ap.add_argument("--napari", action="store_true", help="also time the napari viewer (xvfb-run)")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    image = OUT / "vesicle_default.tif"
    frame = OUT / "render_frame"
    if not image.exists():
        from nemo.synthetic import write_vesicle

        print("writing the default vesicle ...", flush=True)
        write_vesicle(image)
    if args.fresh or not (frame / "defects.parquet").exists():
        from nemo.pipeline import run_frame

        print("nemo run on the default vesicle ...", flush=True)
        run_frame(image, frame)
    from nemo.mesh import load_mesh

    mesh = load_mesh(frame / "mesh.inner.ply")
    print(f"frame: {frame} (inner mesh {len(mesh.vertices)} vertices)")
    nemo = [sys.executable, "-m", "nemo"]
    for label, extra in (("all figures", []), ("matplotlib only", ["--no-surfaces"])):
        out = OUT / "render_figs"
        shutil.rmtree(out, ignore_errors=True)
        wall, peak = _timed(nemo + ["render", str(frame), "-o", str(out), *extra])
        n = len(list(out.glob("*.png")))
        print(f"nemo render ({label}): {n} PNG in {wall:.1f} s wall, peak RSS {peak:.0f} MB")
    from nemo.napari.layers import layer_data

    start = time.perf_counter()
    layers = layer_data(frame)
    print(f"layer_data: {len(layers)} napari layers in {time.perf_counter() - start:.2f} s")
    if args.napari:
        shot = OUT / "render_view.png"
        wall, peak = _timed(["xvfb-run", "-a", "-s", "-screen 0 1400x1000x24", *nemo, "view", str(frame),
                             "--screenshot", str(shot)])
        print(f"nemo view --screenshot (open napari, all layers, screenshot): {wall:.1f} s wall, "
              f"peak RSS {peak:.0f} MB")
    print(json.dumps({"vertices": len(mesh.vertices)}))


if __name__ == "__main__":
    main()
