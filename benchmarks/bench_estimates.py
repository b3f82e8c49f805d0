"""Benchmark: what the data-derived defaults cost in one frame (issue 12: ≤ 20 % of a frame).

``nemo run`` on the paper's vesicle (R = 200 µm, 1 µm voxels) twice per round, alternating:

* **defaults**: every length from the data, so the mesh step estimates the noise and runs the
  blur's topology ladder (``nemo.surface.auto_sigma``), ``psf: auto`` estimates the PSF's z blur
  (``nemo.psf.estimate_psf``) and the curvature step runs the radius pilot
  (``nemo.morphology.default_radius``) for each wall, and the directors their noise-aware
  scale (``nemo.directors.noise_aware_sigma``: a second pass where the first is noisy);
* **pinned**: a config that gives the values the defaults resolved to (``mesh.sigma``,
  ``curvature.radius`` and ``directors.sigma`` read from the first run's outputs, and ``--psf`` the PSF deconvolved, or
  none), so no estimate runs.

The difference of the in-process totals (``summary.json``'s ``total_s``) is the estimates'
cost. The sub-sample snap of the marching-cubes vertices (always on) is reported from its log
line. The image is generated once and not timed; the machine should be otherwise idle.

    .venv/bin/python benchmarks/bench_estimates.py [--radius 200] [--repeat 3] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import yaml
from bench_frame_overhead import vesicle_in_workdir  # same folder


def run_frame(image: Path, out: Path, config: Path | None, extra: list[str] = ()) -> tuple[dict, str]:
    """``nemo run -v`` into ``out`` (with ``extra`` options); its summary.json and log."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "nemo", "run", str(image), "-o", str(out), "-v", *extra]
    cmd += ["--config", str(config)] if config else []
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads((out / "summary.json").read_text()), done.stderr + done.stdout


def resolved_values(out: Path) -> dict:
    """The config that pins what the defaults resolved to in the run in ``out``."""
    from nemo.tables import read_provenance

    summary = json.loads((out / "summary.json").read_text())
    radius = read_provenance(out / "curvature_inner.parquet")["parameters"]["radius"]
    pinned = {"mesh": {"sigma": float(summary["mesh"]["sigma"]), "step": int(summary["mesh"]["step"])},
              "curvature": {"radius": float(radius)}}
    scales = {float(layer["directors"]["sigma"]) for layer in summary["layers"].values()
              if layer.get("directors", {}).get("sigma") is not None}
    if len(scales) == 1:  # the noise-aware director scale (one section for every layer: pinned when they agree)
        pinned["directors"] = {"sigma": scales.pop()}
    return pinned


def resolved_psf(out: Path) -> list[str]:
    """``--psf`` that pins what ``psf: auto`` resolved to in the run in ``out`` (its numbers, or none)."""
    record = json.loads((out / "summary.json").read_text())["mesh"].get("deconvolution") or {}
    return ["--psf", *(str(v) for v in record["psf"])] if record.get("psf") else ["--psf", "none"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--radius", type=float, default=200.0, help="vesicle radius (µm)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds (each runs both, alternating)")
    ap.add_argument("--workdir", help="keep the runs here (default: a temporary folder)")
    args = ap.parse_args()

    work, image = vesicle_in_workdir(args.workdir, "nemo-bench-estimates-", args.radius)
    pinned = work / "pinned.yaml"
    totals: dict[str, list[float]] = {"defaults": [], "pinned": []}
    stages: dict[str, list[dict]] = {"defaults": [], "pinned": []}
    snap = []
    for k in range(args.repeat):
        for name in ("defaults", "pinned"):
            if name == "pinned" and not pinned.exists():
                pinned.write_text(yaml.safe_dump(resolved_values(work / "defaults")))
            extra = resolved_psf(work / "defaults") if name == "pinned" else []
            summary, log = run_frame(image, work / name, pinned if name == "pinned" else None, extra)
            totals[name].append(summary["total_s"])
            stages[name].append(summary["timings_s"])
            snap += [float(s) for s in re.findall(r"snapping \d+ vertices.* done in ([\d.]+) s", log)]
        print(f"round {k + 1}: defaults {totals['defaults'][-1]:.1f} s, pinned {totals['pinned'][-1]:.1f} s",
              flush=True)
    print(f"pinned values: {json.dumps(yaml.safe_load(pinned.read_text()))} {' '.join(resolved_psf(work / 'defaults'))}")
    for name, values in totals.items():
        mid = {key: statistics.median(t[key] for t in stages[name]) for key in stages[name][0]}
        print(f"{name:9s} median {statistics.median(values):6.1f} s, best {min(values):6.1f} s  stages (median): "
              + ", ".join(f"{key} {val:.1f}" for key, val in mid.items()))
    cost = statistics.median(totals["defaults"]) - statistics.median(totals["pinned"])
    base = statistics.median(totals["pinned"])
    print(f"estimates: {cost:+.1f} s = {100 * cost / base:+.0f} % of the pinned frame (medians); "
          f"snap {statistics.median(snap) if snap else float('nan'):.2f} s per run")
    print(f"work folder: {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
