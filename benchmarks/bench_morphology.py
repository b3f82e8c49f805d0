"""Benchmark of the morphology stage: curvature and thickness on a ~500k-vertex mesh.

Targets (issue 3): curvature with 20 000 fitted samples + interpolation to every vertex
≤ 5 s; thickness (one ray per vertex, Embree) for 500k vertices ≤ 3 s. Also times measure,
and (issue 12) the default fitting radius (``default_radius``: pilot fits) against the fit at
that radius, with and without the averaging over the surface (``smooth``); ``--vertices
200000`` is the paper's scale.
Wall and CPU seconds are printed with the load average: on a shared machine the CPU time is
the figure that does not depend on the other jobs.

The test surface is a marching-cubes mesh (1 µm voxels) of a bumpy sphere whose radius is set
from the requested vertex count, and a second, concentric surface 6 µm further out for the
thickness rays. Building the meshes is not timed.

    . .venv/bin/activate && python benchmarks/bench_morphology.py
    python benchmarks/bench_morphology.py --vertices 1000000 --radius 5 --samples 20000
    python benchmarks/bench_morphology.py --vertices 200000 --only-default-radius
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc

import numpy as np
from skimage.measure import marching_cubes

from nemo.mesh import make_mesh
from nemo.morphology import curvature, default_radius, measure, thickness


def bumpy_sphere(radius: float, offset: float = 0.0):
    """Marching-cubes mesh (1 µm voxels) of r = R (1 + 0.05 Y(θ, φ)) + offset."""
    h = int(np.ceil(radius * 1.06 + offset + 3))
    ax = np.arange(-h, h + 1, dtype=np.float32)
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij", sparse=True)
    r = np.sqrt(x * x + y * y + z * z) + np.float32(1e-6)
    bump = 1 + 0.05 * (z / r) * (x / r) * 3 + 0.03 * np.cos(4 * np.arctan2(y, x)) * (1 - (z / r) ** 2)
    field = r - (radius * bump + offset)
    del r, bump
    verts, faces, _, _ = marching_cubes(field, 0.0)
    return make_mesh(verts[:, ::-1] - h, faces)


def timed(label: str, fn, repeat: int):
    """Run ``fn`` ``repeat`` times; print wall and CPU seconds of every run (the first run
    includes one-off costs such as building Embree's BVH of the target mesh)."""
    walls, cpus = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    runs = ", ".join(f"{w:.2f}" for w in walls)
    print(f"{label:58s} best {min(walls):6.2f} s wall, {min(cpus):6.2f} s CPU   (wall per run: {runs})")
    return out, min(walls)


def peak_mb(fn) -> float:
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vertices", type=int, default=500_000, help="approximate vertex count")
    ap.add_argument("--radius", type=float, default=4.0, help="curvature fitting radius (µm)")
    ap.add_argument("--samples", type=int, default=20_000, help="fitted vertices")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only-default-radius", action="store_true", help="time the default radius only")
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")

    # marching cubes at 1 µm gives ~1.5 vertices per µm² of surface
    R = float(np.sqrt(args.vertices / (1.5 * 4 * np.pi)))
    t0 = time.perf_counter()
    inner = bumpy_sphere(R)
    outer = bumpy_sphere(R, offset=6.0)
    print(f"meshes: {len(inner.vertices)} and {len(outer.vertices)} vertices (R ≈ {R:.0f} µm, 1 µm voxels), "
          f"built in {time.perf_counter() - t0:.1f} s (not timed)")
    inner.vertex_normals  # noqa: B018  (cached by trimesh; part of loading a mesh, not of the step)

    bench_default_radius(inner, R, args)
    if args.only_default_radius:
        return

    for fit in ("quadratic", "quartic"):
        df, _ = timed(f"curvature {fit:9s} r={args.radius:g} µm, {args.samples} samples + IDW",
                      lambda fit=fit: curvature(inner, args.radius, n_samples=args.samples, rng=0, fit=fit),
                      args.repeat)
        print(f"{'':58s} median H = {np.nanmedian(df['H']):.5f} 1/µm (1/R = {1 / R:.5f}), "
              f"NaN {int(df['H'].isna().sum())}")
    print(f"{'':58s} peak traced memory (quartic): "
          f"{peak_mb(lambda: curvature(inner, args.radius, n_samples=args.samples, rng=0, fit='quartic')):.0f} MB")

    d, _ = timed(f"thickness outward, {len(inner.vertices)} rays (run 1: + BVH build)",
                 lambda: thickness(inner, outer, "outward"), args.repeat)
    print(f"{'':58s} median {np.nanmedian(d):.3f} µm (6 µm shell), NaN {int(np.isnan(d).sum())}")
    timed(f"thickness nearest, 2 x {len(inner.vertices)} rays", lambda: thickness(inner, outer, "nearest"), 1)
    res, _ = timed(f"measure (area, volume, χ, ∫K dA, mean H), {len(inner.faces)} faces",
                   lambda: measure(inner), 2)
    print(f"{'':58s} χ = {res['euler_characteristic']}, Gauss–Bonnet ratio {res['gauss_bonnet_ratio']:.6f}")


def bench_default_radius(mesh, R: float, args) -> None:
    """Issue 12: the default radius (pilot fits) against the fit it is for."""
    (radius, info), _ = timed("default_radius (pilot ladder of quartic fits)",
                              lambda: default_radius(mesh), args.repeat)
    rungs = ", ".join(f"{x['radius']:.2f}: {x['change'] or 0:.2g}" for x in info["ladder"])
    print(f"{'':58s} radius {radius:.2f} µm = {info['radius_edges']:.1f} edges, limited by "
          f"{info['limited_by']}, R_c {info['curvature_radius']:.1f} µm (object R ≈ {R:.0f}), "
          f"ladder (radius: change) {rungs}, {info['n_probe']} probes")
    df, _ = timed(f"curvature auto at that radius, {args.samples} samples + IDW",
                  lambda: curvature(mesh, radius, n_samples=args.samples, rng=0), args.repeat)
    print(f"{'':58s} fit {df.attrs['fit']}, median H = {np.nanmedian(df['H']):.5f} 1/µm (1/R = {1 / R:.5f})")
    timed("the same without the averaging over the surface (smooth=0)",  # the averaging's share (session 12)
          lambda: curvature(mesh, radius, n_samples=args.samples, rng=0, smooth=0), args.repeat)
    df1, _ = timed("one radius, one width (local_fraction=0, adaptive=False: before session 25)",
                   lambda: curvature(mesh, radius, n_samples=args.samples, rng=0, local_fraction=0, adaptive=False),
                   args.repeat)
    print(f"{'':58s} local fits at the default: {df.attrs['local_fits']} of {len(df)} vertices; median H "
          f"{np.nanmedian(df1['H']):.5f} 1/µm with one radius and width")


if __name__ == "__main__":
    main()
