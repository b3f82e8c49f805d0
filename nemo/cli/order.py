"""``nemo order``: tangential nematic order (Q-tensor average) on a surface."""

from __future__ import annotations

from nemo.cli.common import add_common, output_path, positive

HELP = "tangential Q-tensor average: order parameter S and averaged director"
DESCRIPTION = """\
Lift every director to the tangential tensor n nᵀ − ½(I − N Nᵀ), average the tensors of the
directors within --radius of each target vertex, project onto the target's tangent plane,
remove the trace and diagonalise: S = 2 λ_max, averaged director = its eigenvector
(by default the paper's plain mean; --weights coherency weights each tensor by its director's
coherency). Writes an order table: vertex, S, nx, ny, nz, x, y, z, count (directors averaged;
S is NaN where 0).

examples:
  nemo order inner.ply directors.parquet -o order.parquet --radius 50
  nemo order inner.ply directors.parquet -o order_at_directors.parquet --radius 50 --targets directors
  nemo order inner.ply directors.parquet -o order_weighted.parquet --radius 50 --weights coherency"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh", help="surface mesh the directors were computed on")
    parser.add_argument("directors", help="directors table from 'nemo directors'")
    parser.add_argument("--radius", type=positive(), metavar="UM",
                        help="averaging radius in the mesh's unit (µm): a few patch radii, so that "
                             "each target averages many directors (default 2.5 × the directors' "
                             "patch radius, as the paper's 50 µm for 20 µm patches); S and defects "
                             "blur on larger scales")
    parser.add_argument("--targets", choices=("all", "directors"),
                        help="average at every vertex (default) or at the directors' vertices")
    parser.add_argument("--weights", choices=("none", "coherency"),
                        help="weight of each director in the average: none = the paper's unweighted "
                             "mean (default, config order.weights); coherency = weighted by its "
                             "coherency, so noisy, incoherent patches count less")
    add_common(parser, output_help="order table (.parquet)")


def run(args) -> int:
    import numpy as np

    from nemo import objects, stages
    from nemo.cli.common import mesh_and_table, section_params
    from nemo.tables import read_provenance, write_table

    out = output_path(args.output)
    mesh, dirs, prov = mesh_and_table(args.mesh, args.directors, "directors")
    dparams = read_provenance(args.directors).get("parameters") or {}
    df, params = stages.order(mesh, dirs, section_params(args, "order"),
                              patch_radius=objects.values(dparams, "nominal_radius"))
    write_table(df, out, command="order", directors=str(args.directors), **prov, parameters=params,
                radius=params["radius"])
    s = df["S"].to_numpy()
    s = s[np.isfinite(s)]
    if not s.size:  # a layer without directors (their step said why)
        print(f"{len(df)} targets, no order value: {params.get('skipped') or 'no director in reach'} -> {out}")
        return 0
    print(f"{len(df)} targets: S mean {s.mean():.3f}, median {np.median(s):.3f}, min {s.min():.3f} -> {out}")
    return 0
