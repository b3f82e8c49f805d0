"""``nemo directors``: local fibre directors of a layer on a surface; ``nemo directors import``: another tool's."""

from __future__ import annotations

import argparse

from nemo.cli.common import (
    add_common,
    mesh_and_table,
    number,
    output_path,
    positive,
    seed,
)

HELP = ("tangential fibre directors of a layer (structure tensor of surface micro-images), or "
        "imported from another tool (directors import)")
USAGE = """\
%(prog)s MESH LAYER -o FILE [options]            measure them on a peeled layer
       %(prog)s import MESH POINTS -o FILE [options]     import them from another tool"""
DESCRIPTION = """\
For a random subset of vertices, project the patch of vertices within --patch-radius (or the
--patch-k nearest) onto the centre's tangent plane, interpolate the layer onto a regular grid
(micro-image, --pixel µm), and take the fibre orientation at the centre from the gradient
structure tensor (OrientationPy's recipe, integration scale --sigma pixels). Writes a directors
table: vertex, x, y, z, nx, ny, nz (unit 3D director, tangent), coherency.

Defaults follow the data (nemo.stages): patch radius 0.1 × the object radius sqrt(area/4π)
(at least 8 mean edge lengths), pixel = a quarter of the mean edge length (at least radius/97),
sigma noise-aware (4 pixels, measured again at up to two edges where the directors 2-3.5
windows apart disagree by 9.6° or more in the median, from noise or a sparse texture:
nemo.directors.noise_aware_sigma), 30 patches per patch area (the paper's 12 000 patches of
20 µm on a vesicle of R = 200 µm), capped by the number of vertices. Lengths are in the mesh's
unit (µm). The micro-images are gridded only as far as the centre's structure tensor reads them
(4 sigma plus the gradient and smoothing kernels). A pixel below 0.1 × the mean edge length, or gridded
micro-images wider than 201 pixels, are refused (they only cost time and memory).

Directors made by another tool (a director field at points: CSV, Parquet or NumPy) become a
directors table of the same kind with 'nemo directors import MESH POINTS -o FILE'; its options:
'nemo directors import --help'.

examples:
  nemo directors inner.ply layer.parquet -o directors.parquet --patch-radius 20 --seed 0
  nemo directors inner.ply layer.parquet -o directors.parquet --patch-k 200 --n-patches 5000
  nemo directors import inner.ply fibres.csv -o directors.parquet --basis axis --axis 0 0 1 \\
      --angle-unit degrees"""

IMPORT_DESCRIPTION = """\
Map a director field given at points onto MESH and write a directors table (vertex, x, y, z,
nx, ny, nz, coherency) for nemo order, defects, align and track. POINTS is a CSV/TSV, Parquet,
.npy (structured array) or .npz (one array per column) table with one row per point:

  x, y, z        position in the image's unit (µm), in the mesh's frame: x = column, y = row,
                 z = plane, times the voxel size, the origin at the first voxel
  nx, ny, nz     the director as a 3-D vector (any length and sign; projected onto the tangent
                 plane of the vertex and normalised), or
  angle          the director as an angle in a tangent basis (--basis, --angle-unit), measured
                 from e1 towards N × e1 (N the outward normal: counter-clockwise seen from outside)
  e1x, e1y, e1z  with --basis local: the reference direction e1 of each point's angle
  weight         optional averaging weight (≥ 0; default the coherency, else 1)
  coherency      optional confidence in [0, 1] (default 1)

Column names ignore case. Each point goes to its nearest vertex; points farther than
--max-distance from the surface are refused with a warning and a count (most of them far:
an error, the points are in another unit or frame); vectors (or reference directions) nearly
normal to the surface are dropped. Several points on one vertex are averaged as a nematic
(weighted Q-tensor mean: θ and θ + 180° give θ); the table's coherency is their weighted mean
coherency times their agreement S. The table records the patch radius of NEMO directors of
the same density (30 per patch area), so 'nemo order' defaults to 2.5 × it.

example (a CSV with x,y,z,angle in degrees from the x axis projected onto the surface):
  nemo directors import inner.ply fibres.csv -o directors.parquet --basis axis --axis 1 0 0 \\
      --angle-unit degrees
  nemo order inner.ply directors.parquet -o order.parquet"""


def add_arguments(parser) -> None:
    parser.usage = USAGE
    _add_measure_arguments(parser)
    importer = argparse.ArgumentParser(prog=f"{parser.prog} import", description=IMPORT_DESCRIPTION,
                                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_import_arguments(importer)
    importer.set_defaults(_run=run_import, _command="directors import", _parser=importer)
    _route_import(parser, importer)


def _route_import(parser: argparse.ArgumentParser, importer: argparse.ArgumentParser) -> None:
    """Hand ``nemo directors import ...`` to ``importer``; anything else stays with ``parser``.

    argparse has no optional sub-command in front of positional arguments: the ``nemo`` parser
    passes a subcommand's arguments to that subcommand parser's ``parse_known_args``, which this
    instance routes on its first argument being the word ``import``.
    """
    measure = parser.parse_known_args

    def parse_known_args(args=None, namespace=None):
        args = list(args or [])
        if args[:1] == ["import"]:
            return importer.parse_known_args(args[1:], namespace)
        return measure(args, namespace)

    parser.parse_known_args = parse_known_args


def _add_import_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) to map the directors onto")
    parser.add_argument("points", help="director field at points (.csv, .tsv, .parquet, .npy, .npz)")
    parser.add_argument("--basis", choices=("axis", "local", "frames"),
                        help="tangent basis of an angle column: axis (e1 = the projection of --axis), local "
                             "(e1 = columns e1x, e1y, e1z), frames (NEMO's own: e1 = N × x̂, nemo.geometry)")
    parser.add_argument("--axis", type=number, nargs=3, metavar=("X", "Y", "Z"),
                        help="the fixed axis of --basis axis (e.g. 1 0 0)")
    parser.add_argument("--angle-unit", choices=("degrees", "radians"), help="unit of an angle column")
    parser.add_argument("--max-distance", type=positive(), metavar="UM",
                        help="points farther from the surface are refused (default: 2 mean edge lengths "
                             "of the mesh)")
    parser.add_argument("--min-tangential", type=_fraction, metavar="F",
                        help="drop a vector (or reference e1) whose tangential part is shorter than this "
                             "fraction of it: nearly normal to the surface (default 0.3, i.e. within 17° "
                             "of the normal)")
    add_common(parser, output_help="directors table (.parquet)")


def _fraction(text: str) -> float:
    """argparse type: a number in (0, 1]."""
    value = number(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {text}")
    return value


def _add_measure_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) the layer was peeled on")
    parser.add_argument("layer", help="layer table from 'nemo peel'")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--patch-radius", type=positive(), metavar="UM",
                      help="patch radius in the mesh's unit (µm; default 0.1 × the object radius "
                      "sqrt(area/4π), at least 8 mean edge lengths)")
    size.add_argument("--patch-k", type=positive(int), metavar="K", help="patch = K nearest vertices")
    parser.add_argument("--n-patches", type=positive(int), metavar="N",
                        help="number of patch centres (default: 30 per patch area)")
    parser.add_argument("--pixel", type=positive(), metavar="UM",
                        help="micro-image pixel in the mesh's unit (default: a quarter of the mean edge "
                             "length, at least radius/97)")
    parser.add_argument("--sigma", type=positive(), metavar="PX",
                        help="structure-tensor integration scale in pixels (default: noise-aware, 4 px to two "
                             "edges: nemo.directors.noise_aware_sigma)")
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


def run_import(args) -> int:
    from nemo import stages
    from nemo.cli.common import section_params
    from nemo.import_directors import read_points
    from nemo.mesh import load_mesh
    from nemo.tables import write_table

    out = output_path(args.output)
    mesh = load_mesh(args.mesh)
    points = read_points(args.points)
    df, params = stages.import_directors(mesh, points, section_params(args, "directors_import"),
                                         source=str(args.points))
    unit = getattr(mesh, "units", None) or "um"
    write_table(df, out, command="directors import", points=str(args.points), mesh=str(args.mesh),
                n_vertices=len(mesh.vertices), unit=unit, parameters=params)
    dropped = [f"{params[key]} {what}" for key, what in (
        ("n_far", f"farther than {params['max_distance']:.3g} {unit} from the surface refused"),
        ("n_nearly_normal", "nearly normal to the surface dropped"), ("n_zero_weight", "of weight 0 dropped"),
    ) if params[key]]
    print(f"{params['n_points']} points -> {len(df)} directors ({params['n_shared']} vertices averaged several "
          f"points{'; ' + ', '.join(dropped) if dropped else ''}); median distance to the vertex "
          f"{params['median_distance']:.3g} {unit}, median coherency {df['coherency'].median():.3f} -> {out}")
    return 0
