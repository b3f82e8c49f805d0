"""``nemo thickness``: distance between two surfaces along the vertex normals."""

from __future__ import annotations

import numpy as np

from nemo.cli.common import add_common, non_negative, output_path, positive

HELP = "distance from one surface to another along the vertex normals (ray casting)"
DESCRIPTION = """\
For every vertex V of MESH_FROM a ray is cast along its outward normal N (or against it, or
both) to MESH_TO; the first hit V* gives d = (V* - V)·N (paper eq. inter-mesh-distance):
positive when MESH_TO lies outside along N, negative when inside. No hit, or a hit farther than
--max-distance, gives NaN (never a made-up value). MESH_TO may be MESH_FROM itself (the wall
thickness of a closed shell from its whole surface, both walls in one mesh: use --direction
inward); an object `nemo mesh` found to have one wall (a droplet, split auto) has none: NaN.
The distances are then averaged over the surface (--smooth mean edges; a diffusion along the
mesh that stays on MESH_FROM): each ray's distance scatters by the walls' roughness on a noisy
image; --smooth 0 keeps the paper's per-vertex distances.

Output columns: vertex, thickness (mesh unit, usually µm).

example:
  nemo thickness endoderm.ply ectoderm.ply -o thickness.parquet --direction outward
  nemo thickness inner.ply outer.ply -o d.parquet --direction nearest --max-distance 30"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh_from", help="surface whose vertices get a distance (PLY/OBJ)")
    parser.add_argument("mesh_to", help="surface the rays look for (PLY/OBJ)")
    parser.add_argument("--direction", choices=("outward", "inward", "nearest"),
                        help="along +N, -N, or the closer hit of both (default outward)")
    parser.add_argument("--max-distance", type=positive(float), metavar="UM",
                        help="hits farther than this count as misses (NaN)")
    parser.add_argument("--smooth", type=non_negative, metavar="EDGES",
                        help="average the distances over the surface, width in mean edge lengths of MESH_FROM "
                             "(default 3: a noisy wall's roughness scatters each ray's distance; 0 = the paper's "
                             "per-vertex distances)")
    add_common(parser, output_help="output table (.parquet)")


def run(args) -> int:
    from nemo import stages
    from nemo.cli.common import section_params
    from nemo.mesh import load_mesh
    from nemo.tables import write_table

    out = output_path(args.output)
    mesh_from = load_mesh(args.mesh_from)
    mesh_to = load_mesh(args.mesh_to)
    df, params = stages.thickness(mesh_from, mesh_to, section_params(args, "thickness"))
    d = df["thickness"].to_numpy()
    unit = getattr(mesh_from, "units", None) or "um"
    write_table(df, out, command="thickness", mesh=str(args.mesh_from), n_vertices=len(mesh_from.vertices),
                parameters=params,
                inputs={"mesh_from": str(args.mesh_from), "mesh_to": str(args.mesh_to)}, unit=unit)
    u = "µm" if unit == "um" else unit
    n_nan = int(np.isnan(d).sum())
    print(f"thickness: {len(d)} vertices, rays {params['direction']}")
    if n_nan < len(d):
        a = np.abs(d[~np.isnan(d)])
        print(f"  median |d| = {np.median(a):.4g} {u}, mean |d| = {a.mean():.4g} {u}, "
              f"range [{np.nanmin(d):.4g}, {np.nanmax(d):.4g}] {u}")
    print(f"  NaN (no hit{' within ' + format(args.max_distance, 'g') + ' ' + u if args.max_distance else ''}): "
          f"{n_nan} of {len(d)} vertices ({100 * n_nan / max(len(d), 1):.1f} %)"
          + (f", {params['beyond_view']} of them beyond the field of view (their ray left the image where its "
             "border cut the surface)" if params["beyond_view"] else ""))
    print(f"  -> {out}")
    return 0
