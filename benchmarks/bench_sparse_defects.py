"""Accuracy sweep: defects on sparse director fields (one director per 6-10 µm grid point).

The synthetic vesicle's analytic field (nemo.synthetic.director_field) for each defect preset,
randomly rotated, sampled once per vertex of a Fibonacci-sphere mesh (R = 50 µm) with Gaussian
angle noise, averaged with an order radius of 1.7 × the spacing (as in Eckert et al. 2025),
defects with the data-derived defaults. A case passes when every defect is found once within
2 spacings with the right rounded charge and nothing else is reported.

    python benchmarks/bench_sparse_defects.py                    # the full sweep (≈ 2 min)
    python benchmarks/bench_sparse_defects.py --seeds 3 --presets tetrahedron

Results are recorded in docs/validation.md ("Sparse director fields").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import sparse_fields as sf  # the tests' independent sparse-field builder

from nemo.defects import find_defects
from nemo.order import order
from nemo.synthetic import director_field, preset_defects, projection_pole


def case(preset: str, spacing: float, noise: float, seed: int, radius: float = 50.0) -> dict:
    """Score one sparse case; returns the matching summary of ``sparse_fields.score``."""
    dirs, charges = preset_defects(preset)
    dirs = dirs @ Rotation.random(random_state=seed).as_matrix().T
    mesh = sf.fibonacci_sphere(radius, spacing)
    field = director_field(np.asarray(mesh.vertices), dirs, charges, pole=projection_pole(dirs))
    ddf = sf.vertex_directors(mesh, field, noise, seed)
    d = sf.mean_spacing(mesh)
    df = find_defects(mesh, order(mesh, ddf, 1.7 * d), ddf, avg_radius=1.7 * d)
    sc = sf.score(df, radius * dirs, charges)
    sc["ok"] = bool(sc["found"] == len(dirs) and sc["extras"] == 0 and sc["charge_ok"]
                    and sc["dist"].max() < 2 * d)
    sc["worst"] = float(sc["dist"].max() / d)
    return sc


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["tetrahedron", "five-one", "two-plus-one"])
    ap.add_argument("--spacings", nargs="+", type=float, default=[6.0, 10.0])
    ap.add_argument("--noises", nargs="+", type=float, default=[0.0, 10.0, 20.0])
    ap.add_argument("--seeds", type=int, default=6, help="random rotations per setting (seeds 100, 101, ...)")
    args = ap.parse_args()
    import logging

    logging.getLogger("nemo").setLevel(logging.WARNING)  # the table only, not every step's log
    print("preset        spacing  noise  passed  worst distance / spacing")
    for preset in args.presets:
        for spacing in args.spacings:
            for noise in args.noises:
                res = [case(preset, spacing, noise, 100 + k) for k in range(args.seeds)]
                ok = sum(r["ok"] for r in res)
                print(f"{preset:13s} {spacing:7g} {noise:6g}  {ok:2d}/{len(res):<3d} "
                      f"{max(r['worst'] for r in res):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
