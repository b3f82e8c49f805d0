"""``nemo curvature``: mean and Gaussian curvature at every vertex of a mesh."""

from __future__ import annotations

import argparse

import numpy as np

from nemo.cli.common import add_common, non_negative, output_path, positive, seed

HELP = "mean and Gaussian curvature (H, K) per vertex from local surface fits"
DESCRIPTION = """\
Mean curvature H and Gaussian curvature K at every vertex: a surface z(ξ, η) is fitted by
least squares to the neighbours within --radius of a random subset of vertices, in the frame
of the vertex normal; the results are interpolated to all vertices by inverse-distance weights
over the --k-interp nearest fitted vertices, then averaged over the surface (a diffusion along
the mesh of width --smooth × radius, which averages out the fits' noise; per vertex the widest of
0.5-1 × that width that agrees with the narrower ones, so a tip's peak is less flattened:
--adaptive). With --local-fraction F, a vertex more curved than the radius allows (its radius
of curvature below radius / F) is refitted at a smaller radius. Outward normals: a sphere of radius
R has H = +1/R and K = +1/R² (units 1/µm, 1/µm²).

Fits (--fit): 'quadric' is the paper's z = aξ² + bη² + cξη; 'quadratic' adds linear and
constant terms (insensitive to normal errors); 'quartic' fits all terms up to 4th order
(no r²/R² bias, needs ~60 neighbours); 'auto' (default) takes quartic when the median
vertex has at least 60 neighbours within the radius, else quadratic.

Output columns: vertex, H, K, k1, k2 (principal curvatures, k1 >= k2), d1x..d1z, d2x..d2z
(principal directions), sampled (fit done at that vertex), fit_radius (the radius of the fit
the vertex's values come from). NaN where the radius held fewer than 6 neighbours (a warning
says how many). On an open surface (cut by the image border), a vertex whose ball of the
radius reaches the rim is fitted at the largest radius x 2^(-k/4) whose ball stays off it
(down to 6 mean edges and half the radius; NaN closer): a full, smaller neighbourhood, not
a one-sided one.

example:
  nemo curvature inner.ply -o inner.curvature.parquet --radius 10
  nemo curvature inner.ply -o curv.parquet --radius 10 --samples 20000 --seed 1
  nemo curvature inner.ply -o paper.parquet --radius 10 --fit quadric --smooth 0 --local-fraction 0   # the paper"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) with outward normals")
    parser.add_argument("--radius", type=positive(float), metavar="UM",
                        help="fitting radius in the mesh unit (µm): several edge lengths, below the "
                             "smallest radius of curvature of interest (default from the surface: where pilot "
                             "fits' curvature changes least with the radius, between 4 and 32 mean edges, wider "
                             "on a noisy wall; on an open surface at most the median distance to its rim, "
                             "so half the vertices keep a fit; nemo.morphology.default_radius)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--samples", type=positive(int), metavar="N",
                       help="number of randomly chosen vertices to fit (default: all vertices of small "
                            "meshes, else ~8 per fitting disc, at least 20000 unless their fits "
                            "would hold over 4M neighbour pairs)")
    group.add_argument("--fraction", type=positive(float), metavar="F",
                       help="fraction of vertices to fit, in (0, 1]")
    parser.add_argument("--k-interp", type=positive(int), metavar="K",
                        help="nearest fitted vertices used for the interpolation (default 8)")
    parser.add_argument("--fit", choices=("auto", "quadric", "quadratic", "quartic"),
                        help="fitted surface (default auto)")
    parser.add_argument("--smooth", type=non_negative, metavar="F",
                        help="width of the averaging of H and K over the surface after the fits, as a "
                             "fraction of the radius, 0 to 2 (default 0.35; 0 = the fitted values, as in the paper)")
    parser.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=None,
                        help="average each vertex at the widest of --smooth x radius x (1/2, 1/sqrt(2), 1) that "
                             "agrees with the narrower ones within their noise (default); --no-adaptive: one width")
    parser.add_argument("--local-fraction", type=non_negative, metavar="F",
                        help="fit each vertex at most F x its radius of curvature (from the fits at --radius, averaged): "
                             "a tip or a thin tube is refitted at a smaller radius, down to 6 mean edges and half "
                             "--radius (default 0 = --radius everywhere; 0.65 suits a smooth wall with tips or thin tubes)")
    parser.add_argument("--seed", type=seed, metavar="S", help="random seed of the sample (default 0)")
    add_common(parser, output_help="output table (.parquet)")


def run(args) -> int:
    from nemo import stages
    from nemo.cli.common import section_params
    from nemo.mesh import load_mesh
    from nemo.tables import write_table

    out = output_path(args.output)
    mesh = load_mesh(args.mesh)
    df, params = stages.curvature(mesh, section_params(args, "curvature"))
    unit = getattr(mesh, "units", None) or "um"
    write_table(df, out, command="curvature", mesh=str(args.mesh), n_vertices=len(mesh.vertices),
                parameters=params, inputs={"mesh": str(args.mesh)},
                unit=unit, columns_unit={"H": f"1/{unit}", "K": f"1/{unit}^2"})
    u = "µm" if unit == "um" else unit
    h, k = df["H"].to_numpy(), df["K"].to_numpy()
    n_nan = int(np.isnan(h).sum())
    print(f"curvature: {len(df)} vertices, {params['n_fitted']} fitted ({params['fit_used']} fit, "
          f"radius {params['radius']:.4g} {u})")
    if n_nan < len(df):
        mh, mk = float(np.nanmedian(h)), float(np.nanmedian(k))
        print(f"  median H = {mh:.4g} 1/{u}" + (f"  (1/H = {1 / mh:.4g} {u})" if mh else ""))
        print(f"  median K = {mk:.4g} 1/{u}²" + (f"  (1/sqrt K = {mk ** -0.5:.4g} {u})" if mk > 0 else ""))
        print(f"  H range [{np.nanpercentile(h, 1):.4g}, {np.nanpercentile(h, 99):.4g}] (1st-99th percentile)")
    print(f"  NaN: {n_nan} of {len(df)} vertices")
    print(f"  -> {out}")
    return 0
