"""Deconvolving a known PSF (``datasets.NAME.psf``, ``--psf``; issue 12): cost and accuracy.

Cost: :func:`nemo.psf.deconvolve` (Richardson-Lucy, 30 iterations) on stacks of a few sizes,
seconds and seconds per million voxels, peak memory above the stack; and ``psf: auto``'s estimate
of the z blur (:func:`nemo.psf.estimate_psf`) on a z-blurred random texture of each size.

Accuracy (``--accuracy``): vesicles R 80 µm at dz 2.5 dx under a PSF σ 2.5 / 1 / 1 µm
(``nemo synth … --photons 70 --noise 0 / 12 / 26.5``, seeds 1-3, as
``bench_defect_weights.py``), analysed by ``nemo run`` without and with ``--psf 2.5 1 1``:
defects found, false positives, median / maximum distance to the truth over every matched
defect, the largest charge error, the median shell thickness (truth 10 µm) and the time per frame.

Usage::

    python benchmarks/bench_psf.py [--sizes 86x215x215 200x300x300] [--accuracy] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def cost(shape: tuple[int, int, int], spacing=(2.5, 1.0, 1.0), psf=(2.5, 1.0, 1.0)) -> dict:
    """Seconds and memory of one deconvolution of a random stack of ``shape``."""
    from nemo.psf import deconvolve

    stack = (np.random.default_rng(0).random(shape, dtype=np.float32) * 200).astype(np.uint16)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    _, record = deconvolve(stack, spacing, psf)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"shape": shape, "mvox": stack.size / 1e6, "seconds": seconds, "per_mvox": seconds / (stack.size / 1e6),
            "rss_growth_mb": (peak - before) / 1024, "stack_mb": stack.nbytes / 2**20, "record": record}


def estimate_cost(shape: tuple[int, int, int], spacing=(2.5, 1.0, 1.0)) -> dict:
    """Seconds of ``psf: auto``'s estimate on a random texture of ``shape`` blurred by 2.2 / 0.8 / 0.8 µm."""
    from scipy import ndimage as ndi

    from nemo.psf import estimate_psf

    rng = np.random.default_rng(0)
    stack = ndi.gaussian_filter(rng.random(shape, dtype=np.float32), (2.2 / spacing[0], 0.8, 0.8)) * 1000
    start = time.perf_counter()
    psf, estimate = estimate_psf(stack, spacing)
    return {"seconds": time.perf_counter() - start, "psf": psf, "estimate": estimate}


def run_frame(folder: Path, noise: float, seed: int, psf: bool) -> dict:
    """One frame synthesised (once) and analysed; its score, thickness and time."""
    import pandas as pd
    from bench_defect_weights import synth_vesicle  # the same frames (run from benchmarks/ as a script)

    nemo = [sys.executable, "-m", "nemo"]
    folder.mkdir(parents=True, exist_ok=True)
    image = folder / "v.tif"
    synth_vesicle(image, noise, seed)
    out = folder / ("psf" if psf else "plain")
    start = time.perf_counter()
    subprocess.run([*nemo, "run", str(image), "-o", str(out), *(["--psf", "2.5", "1", "1"] if psf else [])],
                   check=True, capture_output=True)
    seconds = time.perf_counter() - start
    subprocess.run([*nemo, "validate", "score", "--truth", str(image), "--defects",
                    str(out / "defects_fibres.parquet"), "-o", str(out / "score.json")], check=True,
                   capture_output=True)
    score = json.loads((out / "score.json").read_text())
    thickness = pd.read_parquet(out / "thickness.parquet")["thickness"]
    return {"score": score, "thickness": float(thickness.median()), "seconds": seconds, "out": out}


def distances(out: Path, truth_path: Path) -> np.ndarray:
    """Distances of the matched defects (µm)."""
    import pandas as pd

    from nemo.validation.scoring import match_defects, truth_defects

    truth = truth_defects(json.loads(truth_path.read_text()))[["x", "y", "z"]].to_numpy()
    found = pd.read_parquet(out / "defects_fibres.parquet")[["x", "y", "z"]].to_numpy()
    return match_defects(found, truth, 12.0)[2]


def accuracy(workdir: Path) -> None:
    for psf in (False, True):
        dist, found, fp, charge, thick, secs = [], 0, 0, 0.0, [], []
        for noise in (0, 12, 26.5):
            for seed in (1, 2, 3):
                folder = workdir / f"v_{noise:g}_{seed}"
                r = run_frame(folder, noise, seed, psf)
                s = r["score"]
                found, fp = found + s["n_matched"], fp + s["false_positives"]
                charge = max(charge, s["charge_err_max"] or 0.0)
                dist.extend(distances(r["out"], folder / "v.truth.json"))
                thick.append(r["thickness"])
                secs.append(r["seconds"])
                print(f"  {'psf' if psf else 'plain'} noise {noise:g} seed {seed}: {s['n_matched']}/4, "
                      f"max {s['loc_err_max']:.2f} µm, thickness {r['thickness']:.2f} µm, {r['seconds']:.0f} s",
                      flush=True)
        d = np.asarray(dist)
        print(f"{'--psf 2.5 1 1' if psf else 'no psf':>14}: found {found}/36, false positives {fp}, distance median "
              f"{np.median(d):.2f} / max {d.max():.2f} µm, {np.sum(d > 3.0)} beyond 3 µm, charge error max {charge:.3f}, "
              f"thickness median {np.median(thick):.2f} µm, {np.median(secs):.0f} s per frame")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["86x215x215", "200x300x300"])
    ap.add_argument("--accuracy", action="store_true", help="also the nine vesicles (about 10 min)")
    ap.add_argument("--workdir", type=Path, help="keep the frames here (default: a temporary folder)")
    args = ap.parse_args()
    for size in args.sizes:
        c = cost(tuple(int(v) for v in size.split("x")))
        print(f"deconvolve {size} ({c['mvox']:.1f} M voxels, uint16 {c['stack_mb']:.0f} MB): {c['seconds']:.1f} s = "
              f"{c['per_mvox']:.2f} s per M voxels, peak memory +{c['rss_growth_mb']:.0f} MB", flush=True)
        e = estimate_cost(tuple(int(v) for v in size.split("x")))
        print(f"psf auto's estimate {size}: {e['seconds']:.1f} s (z blur {e['psf'] and e['psf'][0]}, "
              f"misfit {e['estimate']['misfit']})", flush=True)
    if args.accuracy:
        if args.workdir:
            accuracy(args.workdir)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                accuracy(Path(tmp))


if __name__ == "__main__":
    main()
