"""Benchmark: wall time of one frame through the workflow vs ``nemo run``, side by side.

The same config file (the paper's vesicle by default: R = 200 µm, 1 µm voxels, every
parameter from the data) is analysed for one frame

* by ``nemo run --config CFG --dataset D -o OUT`` (one process), and
* by ``snakemake --cores 1 --configfile CFG FRAME_FILES`` (the per-stage rules: mesh, measure,
  curvature, thickness, peel, directors, order, defects), with the warm worker (default) and
  without it (``--config worker=False``: a fresh interpreter per job),

alternating, ``--repeat`` times each (best time kept, the input volume generated once and not
timed). Prints the times and the ratios workflow / nemo run, and checks that the defects are
identical.

    .venv/bin/python benchmarks/bench_frame_overhead.py [--radius 200] [--spacing 1] [--repeat 2]
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


def timed(cmd: list[str], cwd: Path) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def vesicle_in_workdir(workdir: str | None, prefix: str, radius: float, spacing: float = 1.0) -> tuple[Path, Path]:
    """The work folder (``workdir`` or a new temporary one) and the synthetic vesicle in it (made once)."""
    work = Path(workdir or tempfile.mkdtemp(prefix=prefix))
    work.mkdir(parents=True, exist_ok=True)
    image = work / "vesicle.tif"
    if not image.exists():
        subprocess.run([sys.executable, "-m", "nemo", "synth", str(image), "--radius", str(radius),
                        "--spacing", *[str(spacing)] * 3], check=True, stdout=subprocess.DEVNULL)
    return work, image


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--radius", type=float, default=200.0, help="vesicle radius (µm)")
    ap.add_argument("--spacing", type=float, default=1.0, help="voxel size (µm)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--workdir", help="keep the runs here (default: a temporary folder)")
    args = ap.parse_args()

    work, image = vesicle_in_workdir(args.workdir, "nemo-bench-frame-", args.radius, args.spacing)
    cfg = {"datasets": {"v": {"path": str(image), "t": [0], "c": [0]}}, "report": {"summary": False}}
    config = work / "frame.yaml"
    config.write_text(yaml.safe_dump(cfg))
    frame = work / "results" / "v" / "t0" / "c0"
    targets = [f"results/v/t0/c0/{f}" for f in ("defects_fibres.parquet", "measure_inner.json", "measure_outer.json",
                                        "curvature_inner.parquet", "curvature_outer.parquet", "thickness.parquet")]
    smk = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work), "--configfile",
           str(config), "--cores", "1", "--quiet", "all"]
    run = [sys.executable, "-m", "nemo", "run", "--config", str(config), "--dataset", "v", "-o", str(work / "run")]
    best = {"nemo run": [], "workflow (warm worker)": [], "workflow (worker off)": []}
    for _ in range(args.repeat):
        shutil.rmtree(work / "run", ignore_errors=True)
        best["nemo run"].append(timed(run, work))
        for name, extra in (("workflow (warm worker)", []), ("workflow (worker off)", ["--config", "worker=False"])):
            shutil.rmtree(work / "results", ignore_errors=True)
            shutil.rmtree(work / ".snakemake", ignore_errors=True)
            best[name].append(timed([*smk, *extra, "--", *targets], work))
    ref = min(best["nemo run"])
    for name, times in best.items():
        t = min(times)
        print(f"{name:24s} {t:7.1f} s (runs: {', '.join(f'{v:.1f}' for v in times)})  ratio {t / ref:.2f}")
    import pandas as pd

    a = pd.read_parquet(frame / "defects_fibres.parquet")
    b = pd.read_parquet(work / "run" / "defects_fibres.parquet")
    same = a[["x", "y", "z", "charge"]].equals(b[["x", "y", "z", "charge"]])
    print(f"defects identical: {same} ({len(a)} defects); work folder: {work}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
