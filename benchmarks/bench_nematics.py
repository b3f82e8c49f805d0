"""Benchmark: peeling, directors and tangential order on the paper-scale vesicle.

Paper scale: the synthetic vesicle of R = 200 µm at 1 µm voxels (``nemo.synthetic.vesicle``
defaults, 450³), its inner surface by marching cubes with a 2 µm step (``nemo.surface``), then

* peel every vertex × 11 samples over [0, 5] µm            (target ≤ 2 s)
* 12 000 directors with 20 µm patches                       (target ≤ 5 s)
* order at every vertex with a 50 µm radius                 (target ≤ 5 s)

plus the director accuracy against the analytic field, and a ≥ 1 M-vertex mesh (the same
image's two walls at a 1 µm marching-cubes step) through peel + directors + order in a fresh
process whose peak RSS is reported. Wall time and CPU time are both printed: on a shared
machine the wall time includes waiting for the CPU.

Run:
    . .venv/bin/activate && python benchmarks/bench_nematics.py            # everything
    python benchmarks/bench_nematics.py --skip-big                         # paper scale only
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def timed(label, fn, *args, **kwargs):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"{label:<48s} wall {wall:6.2f} s   cpu {cpu:6.2f} s", flush=True)
    return out, wall, cpu


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def make_data(workdir: Path, radius: float, big: bool):
    from nemo.mesh import save_mesh
    from nemo.surface import reconstruct, split_mesh
    from nemo.synthetic import vesicle

    data, truth = vesicle(radius=radius, seed=0)
    vol = np.ascontiguousarray(data[0, :, 0])
    np.save(workdir / "volume.npy", vol)
    (workdir / "truth.json").write_text(json.dumps(truth))
    whole = reconstruct(vol, (1.0, 1.0, 1.0), step=2, keep="all")
    inner, _ = split_mesh(whole, by="centre")
    save_mesh(inner, workdir / "inner.ply")
    if big:
        whole1 = reconstruct(vol, (1.0, 1.0, 1.0), step=1, keep="all")
        save_mesh(whole1, workdir / "big.ply")
    return vol, truth, inner


def run_paper_scale(workdir: Path, vol, truth, inner) -> dict:
    from nemo.directors import directors
    from nemo.mesh import mean_edge_length, vertex_normals
    from nemo.order import order
    from nemo.peel import peel
    from nemo.synthetic import truth_directors

    n_vert = len(inner.vertices)
    print(f"inner mesh: {n_vert} vertices, mean edge {mean_edge_length(inner):.2f} µm")
    normals = vertex_normals(inner)
    res = {"vertices": n_vert}
    intensity, res["peel_wall"], res["peel_cpu"] = timed(
        f"peel {n_vert} vertices x 11 samples (linear)", peel, vol, (1, 1, 1), inner.vertices, normals, 0, 5, 11)
    _, res["peel_cubic_wall"], res["peel_cubic_cpu"] = timed(
        "peel, cubic (prefilter included)", peel, vol, (1, 1, 1), inner.vertices, normals, 0, 5, 11, interp="cubic")
    _ = inner.vertex_normals  # cached before timing the next steps
    dirs, res["directors_wall"], res["directors_cpu"] = timed(
        "directors: 12000 patches of 20 µm", directors, inner, intensity, patch_radius=20.0,
        n_patches=12000, rng=0)
    p = dirs[["x", "y", "z"]].to_numpy()
    n = dirs[["nx", "ny", "nz"]].to_numpy()
    err = np.rad2deg(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", n, truth_directors(truth, p))), 0, 1)))
    res["angle_err_median"], res["angle_err_p90"] = float(np.median(err)), float(np.percentile(err, 90))
    print(f"  director angle error vs analytic field: median {res['angle_err_median']:.2f}°, "
          f"90th percentile {res['angle_err_p90']:.2f}°")
    ordr, res["order_wall"], res["order_cpu"] = timed(
        f"order at all {n_vert} vertices, radius 50 µm", order, inner, dirs, 50.0)
    res["S_median"] = float(ordr["S"].median())
    print(f"  S median {res['S_median']:.3f}, min {ordr['S'].min():.3f}")
    return res


def run_big(workdir: Path) -> None:
    """Child process: peel + directors + order on the ≥ 1 M-vertex mesh; print peak RSS."""
    from nemo.directors import directors
    from nemo.mesh import load_mesh, vertex_normals
    from nemo.order import order
    from nemo.peel import peel

    mesh = load_mesh(workdir / "big.ply")
    vol = np.load(workdir / "volume.npy", mmap_mode="r")
    n_vert = len(mesh.vertices)
    print(f"big mesh: {n_vert} vertices ({peak_rss_mb():.0f} MB RSS after loading)", flush=True)
    intensity, *_ = timed(f"big: peel {n_vert} x 11", peel, np.asarray(vol), (1, 1, 1), mesh.vertices,
                          vertex_normals(mesh), 0, 5, 11)
    rss_peel = peak_rss_mb()
    dirs, *_ = timed("big: directors 20 µm patches (default count)", directors, mesh, intensity,
                     patch_radius=20.0, rng=0)
    print(f"  {len(dirs)} directors")
    rss_dir = peak_rss_mb()
    _ = timed(f"big: order at all {n_vert} vertices, 50 µm", order, mesh, dirs, 50.0)
    print(f"big: peak RSS {peak_rss_mb():.0f} MB (after peel {rss_peel:.0f} MB, after directors "
          f"{rss_dir:.0f} MB; includes the 91 MB volume and the mesh)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--radius", type=float, default=200.0)
    parser.add_argument("--skip-big", action="store_true")
    parser.add_argument("--workdir", help="reuse/keep data here (default: a temporary folder)")
    parser.add_argument("--big-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    if args.big_child:
        run_big(Path(args.workdir))
        return 0
    tmp = None
    if args.workdir:
        workdir = Path(args.workdir)
        workdir.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="nemo-bench-")
        workdir = Path(tmp.name)
    print(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    (vol, truth, inner), *_ = timed(f"setup: synthetic vesicle R={args.radius:g} + meshes",
                                     make_data, workdir, args.radius, not args.skip_big)
    res = run_paper_scale(workdir, vol, truth, inner)
    targets = {"peel": 2.0, "directors": 5.0, "order": 5.0}
    for k, target in targets.items():
        ok = "OK" if res[f"{k}_wall"] <= target else ("OK (cpu)" if res[f"{k}_cpu"] <= target else "SLOW")
        print(f"  {k:<10s} {res[f'{k}_wall']:.2f} s wall / {res[f'{k}_cpu']:.2f} s cpu (target {target:g} s) {ok}")
    if not args.skip_big:
        del vol, inner
        subprocess.run([sys.executable, __file__, "--big-child", "--workdir", str(workdir)], check=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
