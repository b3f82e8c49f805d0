"""``nemo directors``: local fibre directors of a layer on a surface."""

from __future__ import annotations

from nemo.cli.common import add_common, mesh_and_table, output_path, positive, seed

HELP = "tangential fibre directors of a layer (structure tensor of surface micro-images)"
DESCRIPTION = """\
For a random subset of vertices, project the patch of vertices within --patch-radius (or the
--patch-k nearest) onto the centre's tangent plane, interpolate the layer onto a regular grid
(micro-image, --pixel µm), and take the fibre orientation at the centre from the gradient
structure tensor (OrientationPy's recipe, integration scale --sigma pixels). Writes a directors
table: vertex, x, y, z, nx, ny, nz (unit 3D director, tangent), coherency.

Defaults follow the data (nemo.stages): patch radius 0.1 × the object radius sqrt(area/4π)
(at least 8 mean edge lengths), pixel = a quarter of the mean edge length (at least radius/97),
sigma = 4 pixels, 30 patches per patch area (the paper's 12 000 patches of 20 µm on a vesicle of
R = 200 µm), capped by the number of vertices. Lengths are in the mesh's unit (µm). A pixel
below 0.1 × the mean edge length, or micro-images wider than 201 pixels, are refused (they
only cost time and memory).

examples:
  nemo directors inner.ply layer.parquet -o directors.parquet --patch-radius 20 --seed 0
  nemo directors inner.ply layer.parquet -o directors.parquet --patch-k 200 --n-patches 5000"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) the layer was peeled on")
    parser.add_argument("layer", help="layer table from 'nemo peel'")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--patch-radius", type=positive(), metavar="UM", help="patch radius in the mesh's unit (µm; default 0.1 × the object radius "
                      "sqrt(area/4π), at least 8 mean edge lengths)")
    size.add_argument("--patch-k", type=positive(int), metavar="K", help="patch = K nearest vertices")
    parser.add_argument("--n-patches", type=positive(int), metavar="N",
                        help="number of patch centres (default: 30 per patch area)")
    parser.add_argument("--pixel", type=positive(), metavar="UM",
                        help="micro-image pixel in the mesh's unit (default: a quarter of the mean edge "
                             "length, at least radius/97)")
    parser.add_argument("--sigma", type=positive(), metavar="PX",
                        help="structure-tensor integration scale in pixels (default 4)")
    parser.add_argument("--seed", type=seed, metavar="S", help="random seed of the centres (default 0)")
    parser.add_argument("--frames", choices=("axis", "smooth"),
                        help="tangent frames: N × x̂ (default) or potpourri3d transport")
    add_common(parser, output_help="directors table (.parquet)")


def run(args) -> int:
    from nemo import stages
    from nemo.cli.common import section_params
    from nemo.tables import field_on_vertices, write_table

    out = output_path(args.output)
    mesh, layer, prov = mesh_and_table(args.mesh, args.layer, "layer")
    intensity = field_on_vertices(layer, "intensity", len(mesh.vertices), args.layer, exact=True)
    df, params = stages.directors(mesh, intensity, section_params(args, "directors"))
    write_table(df, out, command="directors", layer=str(args.layer), **prov, parameters=params)
    print(f"{len(df)} directors (patch radius {params['nominal_radius']:.4g}, pixel {params['pixel']:.3g}), "
          f"median coherency {df['coherency'].median():.3f} -> {out}")
    return 0
