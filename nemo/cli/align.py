"""``nemo align``: nematic alignment between two layers' director fields."""

from __future__ import annotations

import numpy as np

from nemo.cli.common import add_common, output_path, positive
from nemo.errors import NemoError

HELP = "inter-layer alignment c = cos 2(θ_B − θ_A) between two director tables"
DESCRIPTION = """\
For each director of A take the nearest director of B and compute c = cos 2(θ_B − θ_A) in A's
tangent basis (c = 1 parallel, 0 at 45°, −1 orthogonal). With --mesh (the mesh of A), B's
director is first projected onto A's tangent plane. With --max-distance, a director of A with
no director of B that close gets c = NaN. Writes vertex, c, x, y, z, distance and prints the
mean c, the matching distances and a histogram.

example:
  nemo align directors_outer.parquet directors_inner.parquet -o align.parquet --mesh inner.ply \\
      --max-distance 20"""


def add_arguments(parser) -> None:
    parser.add_argument("directors_a", metavar="DIRECTORS_A", help="directors table of layer A")
    parser.add_argument("directors_b", metavar="DIRECTORS_B", help="directors table of layer B")
    parser.add_argument("--mesh", metavar="MESH_A",
                        help="mesh of A's directors (projects B onto A's tangent planes)")
    parser.add_argument("--max-distance", type=positive(), metavar="UM",
                        help="a director of A whose nearest director of B is farther than this "
                             "(mesh unit) gets c = NaN (default: no limit; the distances are printed)")
    parser.add_argument("--bins", type=positive(int), default=10, metavar="N", help="histogram bins (default 10)")
    add_common(parser, output_help="alignment table (.parquet)")


def text_histogram(c: np.ndarray, bins: int = 10, width: int = 40) -> str:
    """A histogram of ``c`` over [−1, 1] as text lines."""
    counts, edges = np.histogram(c[np.isfinite(c)], bins=bins, range=(-1.0, 1.0))
    top = max(int(counts.max()), 1)
    lines = []
    for k, n in enumerate(counts):
        bar = "#" * int(round(width * n / top))
        lines.append(f"  [{edges[k]:+.1f}, {edges[k + 1]:+.1f}{']' if k == bins - 1 else ')'} {n:7d} {bar}")
    return "\n".join(lines)


def run(args) -> int:
    from nemo.mesh import load_mesh
    from nemo.order import alignment
    from nemo.tables import read_table, write_table

    out = output_path(args.output)
    mesh = load_mesh(args.mesh) if args.mesh else None
    n_vertices = len(mesh.vertices) if mesh is not None else None
    a = read_table(args.directors_a, kind="directors", n_vertices=n_vertices)
    b = read_table(args.directors_b, kind="directors")
    df = alignment(a, b, mesh_a=mesh, max_distance=args.max_distance)
    write_table(df, out, command="align", directors_a=str(args.directors_a),
                directors_b=str(args.directors_b), mesh=args.mesh, n_vertices=n_vertices,
                max_distance=args.max_distance)
    if not len(df):  # a layer without directors (its directors step said why)
        print(f"no alignment: a table has no directors -> {out}")
        return 0
    c = df["c"].to_numpy()
    d = df["distance"].to_numpy()
    n_far = int(np.isnan(c).sum())
    if n_far == len(c):
        raise NemoError(
            f"no director of B lies within --max-distance {args.max_distance:g} of a director of A "
            f"(nearest: {np.min(d):.3g}): are the two tables from the same surface and frame?"
        )
    print(f"{len(df)} directors of A: mean c = {np.nanmean(c):+.3f} (median {np.nanmedian(c):+.3f})"
          + (f", {n_far} without a director of B within {args.max_distance:g}" if n_far else ""))
    print(f"distance to the matched director of B: median {np.median(d):.3g}, max {np.max(d):.3g}")
    print(text_histogram(c, bins=max(1, args.bins)))
    print(f"-> {out}")
    return 0
