"""Accuracy of the default curvature radius against the radius, on noisy analytic shapes (issue 12).

Each shape is a ``nemo validate shape`` stack (z-elongated PSF σ 2.5 / 1 / 1 µm, shot +
Gaussian noise at the validation protocol's SNRs), meshed by ``nemo mesh --split none`` at its
defaults. For every mesh: the median relative error |est − exact| / RMS(exact) of H and K per
vertex at fixed radii (mean edges) and at ``nemo.morphology.default_radius`` (the radius where
the pilot's curvature changes least), and the session-10 default of 15 edges for comparison;
each with the default averaging over the surface (``curvature.smooth``, session 12) and with
the fits alone (``smooth=0``).

Usage::

    python benchmarks/bench_curvature_radius.py [--seeds 1 2] [--workdir DIR] [--figure PNG]

Prints a Markdown table (one row per shape, SNR and seed) and, with ``--figure``, plots the
median H error against the radius per SNR (solid: averaged, dashed: the fits alone) with the
default radius marked.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

#: shape, its spec, and the SNRs (photons, Gaussian noise) of config/validation.yaml
SHAPES = {
    "ellipsoid 60 × 45 × 35 µm, dz 2 dx": {"kind": "ellipsoid", "axes": [60, 45, 35], "spacing": [2, 1, 1]},
    "torus 45 / 15 µm, dz 1.5 dx": {"kind": "torus", "major": 45, "minor": 15, "spacing": [1.5, 1, 1]},
}
NOISE = {"∞": {}, "10": {"photons": 31.48, "noise": 12.73}, "5": {"photons": 7.870, "noise": 25.46},
         "3": {"photons": 2.833, "noise": 42.43}}
SCAN_EDGES = (8, 12, 15, 20, 25, 30)


def errors(mesh, truth: dict, radius: float, smooth: float | None = None) -> tuple[float, float]:
    """Median relative H and K errors (fractions) at ``radius`` (``smooth``: None = the default)."""
    from nemo.morphology import curvature
    from nemo.validation.shapes import ellipsoid_curvature, torus_curvature

    p = np.asarray(mesh.vertices) - np.asarray(truth["centre"])
    if truth["kind"] == "torus":
        H0, K0 = torus_curvature(p, truth["major"], truth["minor"])
    else:
        H0, K0 = ellipsoid_curvature(p, truth["axes"])
    df = curvature(mesh, radius, rng=0) if smooth is None else curvature(mesh, radius, rng=0, smooth=smooth)
    H, K = df["H"].to_numpy(), df["K"].to_numpy()
    ok = np.isfinite(H) & np.isfinite(K)
    return (float(np.median(np.abs(H[ok] - H0[ok])) / np.sqrt(np.mean(H0[ok] ** 2))),
            float(np.median(np.abs(K[ok] - K0[ok])) / np.sqrt(np.mean(K0[ok] ** 2))))


def one_case(spec: dict, seed: int, workdir: Path) -> dict:
    """Stack, mesh and errors of one shape."""
    import trimesh

    from nemo.morphology import default_radius, mean_edge_length

    stem = workdir / f"{spec['kind']}_{spec.get('noise', 0)}_{seed}"
    run = [sys.executable, "-m", "nemo"]
    subprocess.run([*run, "validate", "shape", json.dumps({**spec, "seed": seed}), "-o", f"{stem}.tif",
                    "--truth", f"{stem}.json"], check=True, capture_output=True)
    subprocess.run([*run, "mesh", f"{stem}.tif", "-o", f"{stem}.ply", "--split", "none"], check=True,
                   capture_output=True)
    mesh = trimesh.load(f"{stem}.ply", process=False)
    truth = json.loads(Path(f"{stem}.json").read_text())
    h = mean_edge_length(mesh)
    radius, info = default_radius(mesh)
    return {"edge": h, "radius_edges": radius / h, "limited_by": info["limited_by"],
            "default": errors(mesh, truth, radius), "fits": errors(mesh, truth, radius, 0.0),
            "scan": {e: errors(mesh, truth, e * h) for e in SCAN_EDGES},
            "scan_fits": {e: errors(mesh, truth, e * h, 0.0) for e in SCAN_EDGES}}


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SHAPES), figsize=(5.2 * len(SHAPES), 4.0), squeeze=False)
    for ax, shape in zip(axes[0], SHAPES):
        for snr, cases in results[shape].items():
            scan = np.array([[c["scan"][e][0] for e in SCAN_EDGES] for c in cases])
            line, = ax.plot(SCAN_EDGES, 100 * scan.mean(0), marker="o", ms=3, label=f"SNR {snr}")
            fits = np.array([[c["scan_fits"][e][0] for e in SCAN_EDGES] for c in cases])
            ax.plot(SCAN_EDGES, 100 * fits.mean(0), ls="--", lw=0.8, color=line.get_color())
            x = [c["radius_edges"] for c in cases]
            ax.plot(x, [100 * c["default"][0] for c in cases], "*", ms=12, color=line.get_color(), mec="k")
        ax.set(yscale="log", xlabel="fitting radius (mean edges)", ylabel="median |H − H₀| / RMS(H₀) (%)",
               title=shape)
        ax.axhline(2.0 if shape.startswith("ellipsoid") else 3.0, color="grey", ls="--", lw=0.8)
        ax.legend(title="★ default radius; -- fits alone", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--workdir", type=Path, default=None, help="keep the stacks and meshes here")
    ap.add_argument("--figure", type=Path, default=None, help="write the error-against-radius plot (PNG)")
    args = ap.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="nemo-bench-curvature-"))
    workdir.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    print("| shape | SNR | seed | default radius (edges, limited by) | default H / K % | fits alone H / K % | "
          "15 edges H / K % |")
    print("|---|---|---|---|---|---|---|")
    for shape, base in SHAPES.items():
        results[shape] = {}
        for snr, noise in NOISE.items():
            if shape.startswith("torus") and snr == "3":
                continue  # the torus's tube is lost at SNR 3
            spec = {**base, "blur": [2.5, 1, 1], **noise}
            results[shape][snr] = cases = [one_case(spec, seed, workdir) for seed in args.seeds]
            for seed, c in zip(args.seeds, cases):
                print(f"| {shape} | {snr} | {seed} | {c['radius_edges']:.1f} ({c['limited_by']}) | "
                      f"{100 * c['default'][0]:.2f} / {100 * c['default'][1]:.2f} | "
                      f"{100 * c['fits'][0]:.2f} / {100 * c['fits'][1]:.2f} | "
                      f"{100 * c['scan'][15][0]:.2f} / {100 * c['scan'][15][1]:.2f} |", flush=True)
    if args.figure:
        plot(results, args.figure)
        print(f"figure: {args.figure}")
    print(f"work folder: {workdir}")


if __name__ == "__main__":
    main()
