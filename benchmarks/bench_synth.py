"""Benchmark of the synthetic vesicle generator (``nemo synth``).

Measures, for the paper's default vesicle (R = 200 µm, 1 µm voxels, 450^3, one layer) and a few
variants, the wall time of each stage (fibre tracing, rasterisation + blur + shell, writing) and
the peak memory of the process.

    . .venv/bin/activate && python benchmarks/bench_synth.py            # default cases
    python benchmarks/bench_synth.py --quick                            # R = 100 µm only
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _stage_times(**kw) -> dict[str, float]:
    """Time the stages of one vesicle by running them through the public function with logging."""
    import logging

    from nemo import _log
    from nemo.synthetic import vesicle

    times: dict[str, float] = {}

    class Grab(logging.Handler):
        def emit(self, record):
            msg = record.getMessage()
            if " done in " in msg:
                name, t = msg.rsplit(" done in ", 1)
                key = "trace" if name.startswith("tracing") else "rasterise+blur+shell"
                times[key] = times.get(key, 0.0) + float(t.split()[0])

    _log.configure(1)
    _log.logger.handlers[:] = [Grab()]
    t0 = time.perf_counter()
    data, truth = vesicle(**kw)
    times["total"] = time.perf_counter() - t0
    times["voxels"] = float(data.size)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only a R = 100 µm vesicle")
    args = ap.parse_args()
    cases = [("R=100 µm, 1 µm voxels", dict(radius=100.0))]
    if not args.quick:
        cases = [
            ("paper default: R=200 µm, 1 µm voxels, 450^3, 1 layer", {}),
            ("R=200 + noise 10", dict(noise=10.0)),
            ("R=200, dz=2 µm (450x450x225)", dict(spacing=(2.0, 1.0, 1.0))),
            ("R=200, two layers in one channel", dict(second_layer_depth=9.0)),
            ("R=100, 3 frames x 2 channels, 2 layers", dict(radius=100.0, frames=3, frame_rotation=5.0,
                                                           second_layer_depth=9.0, second_layer_channel=1)),
        ]
    print(f"{'case':55s} {'voxels':>12s} {'trace s':>8s} {'raster s':>9s} {'total s':>8s} {'peak MB':>8s}")
    for name, kw in cases:
        t = _stage_times(**kw)
        print(f"{name:55s} {t['voxels']:12.3g} {t.get('trace', np.nan):8.2f} "
              f"{t.get('rasterise+blur+shell', np.nan):9.2f} {t['total']:8.2f} {_peak_mb():8.0f}")
    # the CLI end to end (includes writing the TIFF and the truth JSON)
    from nemo.cli import main as nemo_main

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "vesicle.tif"
        argv = ["synth", str(out)] + (["--radius", "100"] if args.quick else [])
        t0 = time.perf_counter()
        code = nemo_main(argv)
        dt = time.perf_counter() - t0
        print(f"nemo {' '.join(argv[:1] + ['OUT.tif'] + argv[2:])}: exit {code}, {dt:.2f} s wall, "
              f"file {out.stat().st_size / 1e6:.0f} MB, peak RSS {_peak_mb():.0f} MB")


if __name__ == "__main__":
    main()
