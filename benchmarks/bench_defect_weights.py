"""What re-weighting the directors can do for defect localisation under a z-elongated PSF (issue 12).

Vesicles R 80 µm at dz 2.5 dx with a PSF σ 2.5 / 1 / 1 µm (``nemo synth``), analysed by
``nemo run`` at its defaults. Then, for each matched defect, the defect-model fit of
:func:`nemo.defects._refine` is run again on the frame's directors (the first-pass and the
refinement's extra directors, the same window and starting vertex) with other weights:

* ``c``: the coherency (the default: compare the row ``nemo run``, the frames' own positions;
  the refit starts from the vertex nearest the found position, not from the first pass's vertex);
* ``inverse variance``: c² / (1 − c²), relative to the window's median;
* ``visibility``: c times how much of a fibre pattern along the director that a first fit predicts
  survives the (known) PSF: the fibres the PSF wipes out are not looked for;
* ``oracle 30°`` / ``oracle 15°``: c, with every director farther than 30° / 15° from the
  analytic director dropped (an upper bound for any weighting: no measure of a single director
  tells those apart).

Usage::

    python benchmarks/bench_defect_weights.py [--noise 0 12 26.5] [--seeds 1 2 3] [--workdir DIR]
        [--figure PNG]

Prints the median / maximum distance to the truth per weighting, in µm, over every matched
defect. ``--figure`` maps the angle error of the directors around the worst defect
(docs/figures/defect_director_errors_psf.png).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def synth_vesicle(image: Path, noise: float, seed: int) -> None:
    """The benchmark's z-blurred vesicle (R 80 µm, dz 2.5, PSF 2.5 / 1 / 1 µm), once; also used by
    ``bench_psf.py``."""
    if not image.exists():
        subprocess.run([sys.executable, "-m", "nemo", "synth", str(image), "--radius", "80", "--spacing", "2.5", "1",
                        "1", "--blur", "2.5", "1", "1", "--photons", "70", "--noise", f"{noise:g}",
                        "--rotate-random", str(seed), "--seed", str(seed)], check=True, capture_output=True)


def run_frame(noise: float, seed: int, workdir: Path) -> Path:
    """Synthesise and analyse one vesicle; its folder."""
    folder = workdir / f"v_{noise:g}_{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    synth_vesicle(folder / "v.tif", noise, seed)
    if not (folder / "out" / "defects_fibres.parquet").exists():
        subprocess.run([sys.executable, "-m", "nemo", "run", str(folder / "v.tif"), "-o", str(folder / "out")],
                       check=True, capture_output=True)
    return folder


def load(folder: Path) -> dict:
    """Truth, found defects, all directors (with their angle error) and the inner mesh of a frame."""
    import pandas as pd
    import trimesh

    from nemo.synthetic import truth_directors

    truth = json.loads((folder / "v.truth.json").read_text())
    out = folder / "out"
    dirs = pd.concat([pd.read_parquet(out / "directors_fibres.parquet"),
                      pd.read_parquet(out / "refined_fibres.parquet")], ignore_index=True)
    pos, vec = dirs[["x", "y", "z"]].to_numpy(), dirs[["nx", "ny", "nz"]].to_numpy()
    exact = truth_directors(truth, pos)
    error = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", exact, vec)), 0.0, 1.0)))
    return {"truth": truth, "true_xyz": pd.DataFrame(truth["defects"])[["x", "y", "z"]].to_numpy(),
            "found": pd.read_parquet(out / "defects_fibres.parquet"), "pos": pos, "vec": vec,
            "coherency": dirs["coherency"].to_numpy(), "error": error,
            "mesh": trimesh.load(out / "mesh.inner.ply", process=False)}


def visibility(c, err, window, wavelength=8.0, psf=(2.5, 1.0)):
    """c times the visibility, under the known PSF (σz, σxy), of fibres along the director that a
    first c-weighted fit predicts: a fibre pattern of ``wavelength`` keeps exp(−2π² Δσ² / λ²) of
    its contrast, Δσ² the PSF's extra variance across the fibres."""
    from nemo.defects import _fit_defect_model

    xi, eta, theta, t1, t2, rho = window
    w = np.clip(c, 0.05, None)
    core = _fit_defect_model(xi, eta, theta, w, 0.5, rho)
    if core is None:
        return w
    phi = np.arctan2(eta - core[1], xi - core[0])
    model = 0.5 * phi + 0.5 * np.angle(np.sum(w * np.exp(2j * (theta - 0.5 * phi))))
    across = -np.sin(model)[:, None] * t1 + np.cos(model)[:, None] * t2  # across the model's fibres
    extra = (psf[0] ** 2 - psf[1] ** 2) * across[:, 2] ** 2
    return w * np.maximum(np.exp(-2.0 * np.pi**2 * extra / wavelength**2), 0.02)


def weightings() -> dict:
    """Weight of each director in the window: f(coherency, angle error, window)."""
    def inverse_variance(c, err, window):
        c = np.clip(c, 0.05, 0.999)
        w = c * c / (1.0 - c * c)
        return w / np.median(w)

    return {"c (default)": lambda c, err, window: np.clip(c, 0.05, None),
            "inverse variance": inverse_variance,
            "visibility of the model's fibres (known PSF, λ 8 µm)": visibility,
            "oracle 30°": lambda c, err, window: np.clip(c, 0.05, None) * (err < 30.0),
            "oracle 15°": lambda c, err, window: np.clip(c, 0.05, None) * (err < 15.0)}


def refit(frame: dict, x0: np.ndarray, normal: np.ndarray, rho: float, weight) -> np.ndarray:
    """The model fit of ``nemo.defects._refine`` (fit, re-centre, fit again) with ``weight``."""
    from scipy.spatial import cKDTree

    from nemo.defects import _fit_defect_model
    from nemo.geometry import tangent_basis

    tree = cKDTree(frame["pos"])
    t1, t2 = tangent_basis(normal)
    centre = x0
    for _ in range(2):
        j = np.asarray(tree.query_ball_point(centre, rho), dtype=np.int64)
        rel = frame["pos"][j] - x0
        c0 = (centre - x0) @ np.column_stack([t1, t2])
        xi, eta = rel @ t1 - c0[0], rel @ t2 - c0[1]
        d = frame["vec"][j]
        theta = np.arctan2(d @ t2, d @ t1)
        w = weight(frame["coherency"][j], frame["error"][j], (xi, eta, theta, t1, t2, rho))
        keep = w > 0
        if keep.sum() < 12:
            break
        core = _fit_defect_model(xi[keep], eta[keep], theta[keep], w[keep], 0.5, rho)
        if core is None or np.hypot(*(core + c0)) > rho:
            break
        core = core + c0
        centre = x0 + core[0] * t1 + core[1] * t2
    return centre


def distances(frame: dict, match: float = 12.0) -> dict:
    """Distance to the truth of every matched defect per weighting."""
    found = frame["found"]
    xyz = found[["x", "y", "z"]].to_numpy()
    rho = 0.75 * found.attrs["parameters"]["avg_radius"]
    vertices, normals = np.asarray(frame["mesh"].vertices), np.asarray(frame["mesh"].vertex_normals)
    out = {"nemo run": [], **{name: [] for name in weightings()}}
    for true in frame["true_xyz"]:
        d = np.linalg.norm(xyz - true, axis=1)
        k = int(np.argmin(d))
        if d[k] > match:
            continue
        out["nemo run"].append(float(d[k]))
        v = int(found["vertex"].iloc[k])
        for name, weight in weightings().items():
            out[name].append(float(np.linalg.norm(refit(frame, vertices[v], normals[v], rho, weight) - true)))
    return out


def plot_worst(frame: dict, path: Path) -> None:
    """Angle error and coherency of the directors around the frame's worst-placed defect."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from nemo.synthetic import truth_directors

    xyz = frame["found"][["x", "y", "z"]].to_numpy()
    gaps = [np.min(np.linalg.norm(xyz - t, axis=1)) for t in frame["true_xyz"]]
    k = int(np.argmax(np.where(np.array(gaps) < 12.0, gaps, -1.0)))
    true = frame["true_xyz"][k]
    normal = (true - frame["truth"]["centre"]) / np.linalg.norm(true - frame["truth"]["centre"])
    across = np.cross(normal, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    up = np.cross(normal, across)  # the z axis projected onto the tangent plane
    rel = frame["pos"] - true
    u, v = rel @ across, rel @ up
    sel = (np.hypot(u, v) < 12.0) & (rel @ normal > -10.0)
    exact = truth_directors(frame["truth"], frame["pos"][sel])
    found = xyz[int(np.argmin(np.linalg.norm(xyz - true, axis=1)))] - true
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, values, label, clim in ((axes[0], frame["error"][sel], "angle error (°)", (0, 60)),
                                    (axes[1], frame["coherency"][sel], "coherency", (0.5, 1.0))):
        ax.quiver(u[sel], v[sel], exact @ across, exact @ up, color="r", pivot="mid", headwidth=0, scale=0.8,
                  scale_units="xy", width=0.002, alpha=0.5)
        q = ax.quiver(u[sel], v[sel], frame["vec"][sel] @ across, frame["vec"][sel] @ up, values, cmap="viridis",
                      clim=clim, pivot="mid", headwidth=0, scale=0.6, scale_units="xy", width=0.004)
        ax.plot(0, 0, "r+", ms=18, mew=3, label="true core")
        ax.plot(found @ across, found @ up, "bx", ms=14, mew=3, label=f"found ({np.linalg.norm(found):.1f} µm)")
        ax.set(aspect="equal", xlabel="across z (µm)", ylabel="projected z axis (µm)", title=label)
        fig.colorbar(q, ax=ax, shrink=0.8)
    axes[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(f"directors around a +½ defect, |n_z| = {abs(normal[2]):.2f} (red: exact)")
    fig.tight_layout()
    fig.savefig(path, dpi=70)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 12.0, 26.5])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--workdir", type=Path, default=None, help="keep the stacks and results here")
    ap.add_argument("--figure", type=Path, default=None, help="map the directors around the worst defect (PNG)")
    args = ap.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="nemo-bench-defect-weights-"))
    totals: dict = {"nemo run": [], **{name: [] for name in weightings()}}
    worst = (-1.0, None)
    for noise in args.noise:
        for seed in args.seeds:
            frame = load(run_frame(noise, seed, workdir))
            d = distances(frame)
            for name in totals:
                totals[name] += d[name]
            if d["c (default)"] and max(d["c (default)"]) > worst[0]:
                worst = (max(d["c (default)"]), frame)
            print(f"noise {noise:g}, seed {seed}: {len(d['c (default)'])} matched, c weights "
                  f"{np.round(d['c (default)'], 2).tolist()} µm", flush=True)
    print("\n| weights | matched | median / max distance (µm) | summed (µm) |\n|---|---|---|---|")
    for name, d in totals.items():
        d = np.asarray(d)
        print(f"| {name} | {len(d)} | {np.median(d):.2f} / {d.max():.2f} | {d.sum():.1f} |")
    if args.figure and worst[1] is not None:
        plot_worst(worst[1], args.figure)
        print(f"figure: {args.figure}")
    print(f"work folder: {workdir}")


if __name__ == "__main__":
    main()
