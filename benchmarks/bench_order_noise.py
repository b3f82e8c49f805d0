"""Benchmark: S contrast between ordered regions and defect cores at low SNR, weighted vs unweighted.

For independent synthetic vesicles (``nemo.synthetic.vesicle``: different radii, seeds and
random rotations of the tetrahedral +1/2 defect set) at noise levels giving a fibre SNR of
about 10, 5 and 3, the layer is peeled and its directors computed with the stage defaults
(``nemo.stages``), then the order table is computed with ``order.weights`` = ``none`` (the
paper's mean) and ``coherency``, and the defects are found on each (default parameters).

* SNR = (object − background) / noise σ with object − background = the peak of an isolated
  blurred fibre above the shell (``fibre_intensity`` × 255 = 153; overlapping fibres add up
  and clip at 255, so a percentile of the image would overstate it). The shell against the
  outside (0.25 × 255 = 64) has SNR ≈ 64 / σ (``shell_snr``). The fibres do not depend on the
  noise (separate random streams), so every noise level shows the same fibres.
* contrast = median S over vertices farther than 2 × the averaging radius from every true
  defect − median S within 0.5 × the radius of a true defect (distances along the sphere).
* defects: found within the averaging radius of a true defect with charge +1/2 (hits),
  others (extra); the position error (arc distance to the true defect, µm).

The mesh is the inner wall of the noise-free image (the segmentation is not under test), so
every noise level and weighting shares one mesh.

Run:
    . .venv/bin/activate && python benchmarks/bench_order_noise.py          # 3 vesicles x 4 noise levels
    python benchmarks/bench_order_noise.py --quick                          # one vesicle
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

#: (radius µm, seed, rotation seed) of the independent vesicles.
CASES = ((60.0, 1, 11), (80.0, 2, 12), (70.0, 3, 13))
SNRS = (None, 10.0, 5.0, 3.0, 2.0)
#: Peak of an isolated blurred fibre above the shell (``vesicle(fibre_intensity=0.6)``, 0-255).
FIBRE_PEAK = 0.6 * 255


def clean_setup(radius: float, seed: int, rot: int):
    """Inner wall of the noise-free image, the vesicle's centre and the true defect directions."""
    from nemo import stages
    from nemo.synthetic import vesicle

    data, truth = vesicle(radius=radius, seed=seed, rotate=rot)
    meshes, _ = stages.mesh(data[0, :, 0], (1.0, 1.0, 1.0), {"split": "centre"})
    dirs = np.array([[d["ux"], d["uy"], d["uz"]] for d in truth["defects"] if d["layer"] == 0])
    return meshes["inner"], np.asarray(truth["centre"], dtype=float), dirs


def noisy_directors(mesh, radius, seed, rot, sigma):
    """Layer intensity and directors (stage defaults) of the image with noise ``sigma``."""
    from nemo import stages
    from nemo.synthetic import vesicle

    data, _ = vesicle(radius=radius, seed=seed, rotate=rot, noise=sigma)
    vol = data[0, :, 0]
    ldf, _ = stages.peel(vol, (1.0, 1.0, 1.0), mesh, {"range": [0, 5]})
    intensity = ldf["intensity"].to_numpy()
    ddf, dp = stages.directors(mesh, intensity, {"seed": 0})
    return intensity, ddf, dp


def contrast(mesh, s, centre, dirs, avg_radius):
    """Median S far from (> 2 r) minus near (< 0.5 r) the true defects (arc distance)."""
    v = np.asarray(mesh.vertices) - centre
    rad = np.linalg.norm(v, axis=1)
    arc = rad[:, None] * np.arccos(np.clip((v / rad[:, None]) @ dirs.T, -1, 1))
    d = arc.min(axis=1)
    far, near = np.nanmedian(s[d > 2 * avg_radius]), np.nanmedian(s[d < 0.5 * avg_radius])
    return float(far), float(near), float(far - near)


def defect_hits(found, centre, dirs, radius, avg_radius):
    """True defects with a +1/2 found within ``avg_radius``, extra defects, and the arc distance
    (µm, on the sphere of ``radius``) from each hit true defect to its nearest such defect."""
    if len(found) == 0:
        return 0, 0, np.array([])
    u = found[["x", "y", "z"]].to_numpy() - centre
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    arc = radius * np.arccos(np.clip(u @ dirs.T, -1, 1))  # (found, true)
    ok = (arc < avg_radius) & (found["charge_rounded"].to_numpy()[:, None] == 0.5)
    hit = ok.any(axis=0)
    err = np.where(ok, arc, np.inf).min(axis=0)[hit]
    return int(hit.sum()), int(len(found) - ok.any(axis=1).sum()), err


def run_case(radius, seed, rot, rows):
    from nemo import stages

    mesh, centre, dirs = clean_setup(radius, seed, rot)
    print(f"R {radius:g} seed {seed} rotation {rot}: {len(mesh.vertices)} vertices", flush=True)
    for snr in SNRS:
        sigma = 0.0 if snr is None else FIBRE_PEAK / snr
        t0 = time.perf_counter()
        intensity, ddf, dp = noisy_directors(mesh, radius, seed, rot, sigma)
        for weights in ("none", "coherency"):
            odf, op = stages.order(mesh, ddf, {"weights": weights}, patch_radius=dp["nominal_radius"])
            s = odf["S"].to_numpy()
            far, near, c = contrast(mesh, s, centre, dirs, op["radius"])
            found, _, _ = stages.defects(mesh, odf, ddf, {}, avg_radius=op["radius"], intensity=intensity,
                                         director_params=dp)
            hits, extra, err = defect_hits(found, centre, dirs, radius, op["radius"])
            row = {"R": radius, "seed": seed, "snr": snr, "sigma": round(sigma, 2),
                   "shell_snr": None if not sigma else round(0.25 * 255 / sigma, 2), "weights": weights,
                   "coherency_median": float(ddf["coherency"].median()), "S_far": far, "S_near": near,
                   "contrast": c, "S_median": float(np.nanmedian(s)), "hits": hits, "extra": extra,
                   "n_defects": int(len(found)),
                   "error_mean": float(err.mean()) if len(err) else None,
                   "error_max": float(err.max()) if len(err) else None}
            rows.append(row)
            print(f"  SNR {str(snr):>4s} σ {sigma:5.1f} {weights:<9s} coh {row['coherency_median']:.2f}  "
                  f"S far {far:.3f} near {near:.3f} contrast {c:.3f}  defects {hits}/4 +{extra} extra, "
                  f"error mean {row['error_mean']:.2f} max {row['error_max']:.2f} µm",
                  flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one vesicle only")
    ap.add_argument("--json", help="write the rows to this JSON file")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rows: list[dict] = []
    for case in CASES[:1] if args.quick else CASES:
        run_case(*case, rows)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
