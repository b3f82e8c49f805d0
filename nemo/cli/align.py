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

Noise in either layer pulls the mean of c towards 0 (a director off by ε counts cos 2ε): with
both layers' order tables (--order-a, --order-b) the table also gets c_avg, the same measure
between the averaged directors n_avg, and weight = S_A · S_B, and the S-weighted mean of c_avg
is printed (two noisy layers at 90°: mean c −0.47, c_avg −0.89).

example:
  nemo align directors_outer.parquet directors_inner.parquet -o align.parquet --mesh inner.ply \\
      --max-distance 20
  nemo align directors_a.parquet directors_b.parquet --order-a order_a.parquet \\
      --order-b order_b.parquet --mesh inner.ply -o align.parquet"""


def add_arguments(parser) -> None:
    parser.add_argument("directors_a", metavar="DIRECTORS_A", help="directors table of layer A")
    parser.add_argument("directors_b", metavar="DIRECTORS_B", help="directors table of layer B")
    parser.add_argument("--mesh", metavar="MESH_A",
                        help="mesh of A's directors (projects B onto A's tangent planes)")
    parser.add_argument("--max-distance", type=positive(), metavar="UM",
                        help="a director of A whose nearest director of B is farther than this "
                             "(mesh unit) gets c = NaN (default: no limit; the distances are printed)")
    parser.add_argument("--order-a", metavar="ORDER_A", help="order table of layer A (nemo order), for c_avg")
    parser.add_argument("--order-b", metavar="ORDER_B", help="order table of layer B (nemo order), for c_avg")
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
    if (args.order_a is None) != (args.order_b is None):
        raise NemoError("give both --order-a and --order-b (the two layers' order tables), or neither")
    orders = {} if args.order_a is None else {"order_a": read_table(args.order_a, kind="order"),
                                              "order_b": read_table(args.order_b, kind="order")}
    df = alignment(a, b, mesh_a=mesh, max_distance=args.max_distance, **orders)
    write_table(df, out, command="align", directors_a=str(args.directors_a),
                directors_b=str(args.directors_b), mesh=args.mesh, n_vertices=n_vertices,
                max_distance=args.max_distance, order_a=args.order_a, order_b=args.order_b)
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
    if orders:
        from nemo.summary import c_avg_means

        avg = c_avg_means(df)
        print(f"averaged directors: c_avg = {avg['c_avg_mean']:+.3f} (weighted by S_A · S_B; median "
              f"{avg['c_avg_median']:+.3f})")
    print(f"distance to the matched director of B: median {np.median(d):.3g}, max {np.max(d):.3g}")
    print(text_histogram(c, bins=max(1, args.bins)))
    print(f"-> {out}")
    return 0
