"""Cost and effect of the sub-voxel refinement (``reconstruct(refine=...)``) on a paper-scale frame.

Target (issue 12): the refinement adds at most 20 % to the surface reconstruction of a
paper-scale frame (450³ voxels, R = 200 µm, 1 µm voxels, marching-cubes step 2, the default
of ``nemo mesh`` for such a stack). The image is the one of ``bench_mesh.py``
(``benchmarks/out/``, written once).

Usage::

    python benchmarks/bench_refine.py [--repeat 3] [--fresh]

Prints, for the defaults, ``refine`` on and ``edge: profile`` (the level from the walls' fitted
profiles, opt-in), the best wall time of :func:`nemo.surface.reconstruct` (blur,
threshold, marching cubes, smoothing, refinement), the added fraction, and the inner and outer
wall radii (median vertex distance to the true centre) against the truth.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    from bench_mesh import vesicle

    from nemo.io import read_stack
    from nemo.surface import reconstruct, split_mesh

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--fresh", action="store_true")
    args = ap.parse_args()
    image, info = vesicle(args.fresh)
    vol, meta = read_stack(image)
    spacing = tuple(float(s) for s in meta.spacing)
    centre = np.asarray(info["centre"], float)
    times = {}
    variants = {"default": {}, "refine": {"refine": True}, "edge profile": {"edge": "profile"}}
    for name, options in variants.items():
        best = np.inf
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            mesh = reconstruct(vol, spacing, step=2, keep="all", **options)
            best = min(best, time.perf_counter() - t0)
        times[name] = best
        inner, outer = split_mesh(mesh, centre=centre)
        r_in = np.median(np.linalg.norm(inner.vertices - centre, axis=1))
        r_out = np.median(np.linalg.norm(outer.vertices - centre, axis=1))
        print(f"{name:12}: {best:6.2f} s, {len(mesh.vertices)} vertices; level {mesh.metadata['nemo_surface']['level']:.4g}; "
              f"inner wall {r_in:.3f} (truth {info['radius']:g}), outer {r_out:.3f}, thickness {r_out - r_in:.3f} µm")
    for name in ("refine", "edge profile"):
        print(f"{name} adds {times[name] - times['default']:.2f} s = {100 * (times[name] / times['default'] - 1):.1f} %")


if __name__ == "__main__":
    main()
