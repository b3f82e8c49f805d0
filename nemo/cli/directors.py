"""``nemo directors``: local fibre directors of a layer on a surface."""

from __future__ import annotations

from nemo.cli.common import add_common, mesh_and_table, output_path, positive

HELP = "tangential fibre directors of a layer (structure tensor of surface micro-images)"
DESCRIPTION = """\
For a random subset of vertices, project the patch of vertices within --patch-radius (or the
--patch-k nearest) onto the centre's tangent plane, interpolate the layer onto a regular grid
(micro-image, --pixel µm), and take the fibre orientation at the centre from the gradient
structure tensor (OrientationPy's recipe, integration scale --sigma pixels). Writes a directors
table: vertex, x, y, z, nx, ny, nz (unit 3D director, tangent), coherency.

The patch size is required (--patch-radius or --patch-k). The other defaults follow the data:
pixel = half the mean edge length (at least radius/20), sigma = half the patch radius in
pixels, 30 patches per patch area (the paper's 12 000 patches of 20 µm on a vesicle of
R = 200 µm), capped by the number of vertices. Lengths are in the mesh's unit (µm). A pixel
below 0.1 × the mean edge length, or micro-images wider than 201 pixels, are refused (they
only cost time and memory).

examples:
  nemo directors inner.ply layer.parquet -o directors.parquet --patch-radius 20 --seed 0
  nemo directors inner.ply layer.parquet -o directors.parquet --patch-k 200 --n-patches 5000"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) the layer was peeled on")
    parser.add_argument("layer", help="layer table from 'nemo peel'")
    size = parser.add_mutually_exclusive_group(required=True)
    size.add_argument("--patch-radius", type=positive(), metavar="UM", help="patch radius in the mesh's unit (µm)")
    size.add_argument("--patch-k", type=positive(int), metavar="K", help="patch = K nearest vertices")
    parser.add_argument("--n-patches", type=positive(int), metavar="N",
                        help="number of patch centres (default: 30 per patch area)")
    parser.add_argument("--pixel", type=positive(), metavar="UM",
                        help="micro-image pixel in the mesh's unit (default: half the mean edge length, at least "
                             "radius/20)")
    parser.add_argument("--sigma", type=positive(), metavar="PX",
                        help="structure-tensor integration scale in pixels (default: half the patch radius)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed of the centres (default 0)")
    parser.add_argument("--frames", choices=("axis", "smooth"), default="axis",
                        help="tangent frames: N × x̂ (default) or potpourri3d transport")
    add_common(parser, output_help="directors table (.parquet)")


def run(args) -> int:
    from nemo.directors import directors
    from nemo.tables import field_on_vertices, write_table

    out = output_path(args.output)
    mesh, layer, prov = mesh_and_table(args.mesh, args.layer, "layer")
    intensity = field_on_vertices(layer, "intensity", len(mesh.vertices), args.layer, exact=True)
    df = directors(
        mesh, intensity, patch_radius=args.patch_radius, patch_k=args.patch_k,
        n_patches=args.n_patches, pixel=args.pixel, sigma=args.sigma, frames=args.frames,
        rng=args.seed,
    )
    write_table(
        df, out, command="directors", layer=str(args.layer), **prov,
        patch_radius=args.patch_radius, patch_k=args.patch_k, n_patches=args.n_patches,
        pixel=args.pixel, sigma=args.sigma, seed=args.seed, frames=args.frames,
    )
    print(f"{len(df)} directors, median coherency {df['coherency'].median():.3f} -> {out}")
    return 0
