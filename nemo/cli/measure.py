"""``nemo measure``: area, volume, topology and Gauss–Bonnet check of a mesh."""

from __future__ import annotations

import math

from nemo.cli.common import add_common, print_json

HELP = "area, volume, Euler characteristic, genus, ∫K dA (Gauss–Bonnet), mean H of a mesh"
DESCRIPTION = """\
Global morphology of a surface mesh: area, enclosed volume (closed meshes only), number of
connected components and boundary loops, Euler characteristic χ and genus, the discrete
∫K dA (angle defects) with its Gauss–Bonnet ratio (∫K dA + ∫k_g ds) / 2πχ, and the
area-weighted mean curvature (from dihedral angles). With --curvature, the same integrals from
a 'nemo curvature' table (a check of the fitted K: the ratio should be close to 1).

example:
  nemo measure inner.ply
  nemo measure inner.ply --curvature inner.curvature.parquet --json"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ)")
    parser.add_argument("--curvature", metavar="FIELDS.parquet",
                        help="curvature table of this mesh (nemo curvature) for the fitted ∫K dA")
    parser.add_argument("--json", action="store_true", help="print a JSON object")
    add_common(parser, output=False)


def _fmt(x, spec=".6g") -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def run(args) -> int:
    from nemo.mesh import load_mesh
    from nemo.stages import measure
    from nemo.tables import read_table

    mesh = load_mesh(args.mesh, manifold=False)  # measure reports a non-manifold surface in its notes
    curv = read_table(args.curvature, "curvature", n_vertices=len(mesh.vertices)) if args.curvature else None
    res = measure(mesh, curv)
    if args.json:
        print_json(res)
        return 0
    u = "µm" if res["unit"] == "um" else res["unit"]
    print(f"mesh               {args.mesh}: {res['n_vertices']} vertices, {res['n_faces']} faces")
    print(f"area               {_fmt(res['area'])} {u}²")
    open_note = "" if res["is_watertight"] else "  (open mesh: no enclosed volume)"
    print(f"volume             {_fmt(res['volume'])} {u}³{open_note}")
    print(f"watertight         {res['is_watertight']}")
    print(f"components         {res['n_components']}  (boundary loops: {res['n_boundary_loops']})")
    print(f"Euler χ / genus    {res['euler_characteristic']} / {_fmt(res['genus'], '')}")
    print(f"∫K dA (discrete)   {_fmt(res['integral_K'])}   2πχ = {2 * math.pi * res['euler_characteristic']:.6g}"
          + (f"   ∫k_g ds = {res['boundary_turning']:.6g}" if res["n_boundary_loops"] else ""))
    print(f"Gauss–Bonnet ratio {_fmt(res['gauss_bonnet_ratio'])}")
    print(f"mean H             {_fmt(res['mean_H'])} 1/{u}   mean K {_fmt(res['mean_K'])} 1/{u}²")
    if "integral_K_fit" in res:
        print(f"∫K dA (fitted)     {_fmt(res['integral_K_fit'])}   Gauss–Bonnet ratio {_fmt(res['gauss_bonnet_ratio_fit'])}")
        print(f"mean H, K (fitted) {_fmt(res['mean_H_fit'])} 1/{u}, {_fmt(res['mean_K_fit'])} 1/{u}²")
    for note in res["notes"]:
        print(f"note: {note}")
    return 0
