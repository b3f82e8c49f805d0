"""``nemo defects``: topological defects of a director field and their curvature-corrected charge."""

from __future__ import annotations

from nemo.cli.common import add_common, number, output_path, positive

HELP = "find topological defects (low S) and their charge, corrected for Gaussian curvature"
DESCRIPTION = """\
Locate topological defects where the nematic order S of ORDER is low (lowest S first, other
candidates within --min-distance suppressed; geodesic distances are shortest paths along mesh
edges, a few % longer than true geodesics, and the contour uses the same ones), refine each
position below the vertex spacing from the raw DIRECTORS, and measure the charge on a closed
contour at geodesic radius --contour-radius: winding of the director + (1/2π)∫K dA over the
enclosed patch (K from --curvature, else the mesh's angle defects). On a closed surface the
charges add up to the Euler characteristic χ; the check is printed and stored in the table.

Defaults follow the data: threshold 0.5 × the 90th percentile of S, suppression radius = the
averaging radius of ORDER (read from its metadata), contour 1.5 × that radius, the refinement's
defect-model fit over the directors within 1.125 × that radius (at most 0.75 × the surface's
size, but not below 0.75 × the radius; the table's fit_radius). The table's fit_residual (degrees)
is how far the directors are from that model, fit_scatter how much of it is their own noise (the
residual's scatter between neighbouring directors) and fit_uncertainty (µm) the core's standard
error with that noise; the summary flags a defect whose residual exceeds its scatter by more than
20° (√(residual² − scatter²): misplaced, or an unreadable texture) or whose uncertainty exceeds 0.15
of the fit radius (directors too noisy or sparse to place it).

example:
  nemo defects mesh.inner.ply order.parquet directors.parquet -o defects.parquet
  nemo defects mesh.inner.ply order.parquet directors.parquet --layer layer.parquet \\
      -o defects.parquet        # + refinement pass with extra directors near each defect
  nemo defects mesh.ply order.parquet directors.parquet --curvature curvature.parquet \\
      --contour-radius 40 -o defects.parquet"""


def add_arguments(parser) -> None:
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) the tables were computed on")
    parser.add_argument("order", help="order table (nemo order)")
    parser.add_argument("directors", help="directors table (nemo directors)")
    parser.add_argument("--curvature", metavar="FIELDS.parquet",
                        help="curvature table (nemo curvature): K x vertex area for the K term "
                             "(default: the mesh's angle defects, exact discrete Gauss-Bonnet)")
    parser.add_argument("--s-threshold", type=positive(), metavar="S",
                        help="candidates have S below this (default 0.5 x P90 of S)")
    parser.add_argument("--min-distance", type=positive(), metavar="UM",
                        help="geodesic suppression radius in µm (default: the averaging radius)")
    parser.add_argument("--max-defects", type=positive(int), metavar="N", help="report at most N defects")
    parser.add_argument("--contour-radius", type=positive(), metavar="UM",
                        help="geodesic radius of the charge contour in µm (default 1.5 x averaging radius)")
    parser.add_argument("--avg-radius", type=positive(), metavar="UM",
                        help="averaging radius of ORDER (default: from its metadata, else estimated)")
    parser.add_argument("--no-curvature-correction", action="store_true",
                        help="drop the (1/2π)∫K dA term (the flat-surface winding only)")
    parser.add_argument("--curvature-source", choices=("contour", "angle-defects", "table"),
                        help="K term: Gauss-Bonnet on the charge contour's own turning (default), the "
                             "enclosed vertices' angle defects, or --curvature (the default when given)")
    parser.add_argument("--winding-field", choices=("average", "directors"),
                        help="director on the contour: averaged field of ORDER or nearest raw director")
    parser.add_argument("--refine", choices=("model", "q", "none"),
                        help="sub-vertex refinement: defect-model fit to the raw directors, zero of "
                             "the averaged Q, or none")
    parser.add_argument("--layer", metavar="LAYER.parquet",
                        help="the peeled layer DIRECTORS was measured on: enables the refinement pass "
                             "(extra directors around each first-pass defect, same parameters)")
    parser.add_argument("--refine-directors", type=number, metavar="F",
                        help="with --layer: fraction of the vertices near each defect that get an "
                             "extra director (default 0.5; 0 = no refinement pass)")
    parser.add_argument("--refined", metavar="FILE.parquet",
                        help="with --layer: also write the refinement directors to this table")
    parser.add_argument("--candidates", metavar="FILE.parquet",
                        help="also write every examined low-S candidate (position, S, charge, contour S "
                             "and its acceptance floor, largest winding step and its limit, accepted, "
                             "reason) to this table")
    add_common(parser, output_help="output defects table (.parquet)")


def _averaging_radius(order_path: str) -> float | list[float | None] | None:
    """The order table's averaging radius from its provenance: one per object on a mesh of several,
    None for an object without one (estimated from its S field, as ``nemo run`` does: one object
    without an order, e.g. a cap cut by the border, leaves the others' radii as they are)."""
    from nemo import objects
    from nemo.tables import read_provenance

    prov = read_provenance(order_path)
    params = prov.get("parameters") or {}
    radius = objects.values(params, "radius") if params else prov.get("radius")
    if isinstance(radius, list):
        return [float(r) if _usable(r) else None for r in radius]
    return float(radius) if _usable(radius) else None


def _usable(radius) -> bool:
    return isinstance(radius, (int, float)) and not isinstance(radius, bool) and radius > 0


def run(args) -> int:
    import warnings

    from nemo import stages
    from nemo.cli.common import section_params
    from nemo.errors import NemoError, NemoWarning
    from nemo.mesh import load_mesh
    from nemo.tables import field_on_vertices, read_provenance, read_table, write_table

    out = output_path(args.output)
    cand_out = output_path(args.candidates) if args.candidates else None
    mesh = load_mesh(args.mesh)
    n = len(mesh.vertices)
    odf = read_table(args.order, kind="order", n_vertices=n)
    ddf = read_table(args.directors, kind="directors", n_vertices=n)
    avg = args.avg_radius if args.avg_radius is not None else _averaging_radius(args.order)
    k = None
    if args.curvature:
        cdf = read_table(args.curvature, kind="curvature", n_vertices=n)
        k = field_on_vertices(cdf, "K", n, args.curvature, exact=True)
        if not (k == k).any():
            raise NemoError(f"{args.curvature} has no finite K value; recompute it with a larger --radius")
        if args.curvature_source is None:
            args.curvature_source = "table"  # a curvature table given is a curvature table used
        elif args.curvature_source != "table":
            warnings.warn(f"--curvature {args.curvature} is not used: --curvature-source {args.curvature_source} "
                          "takes the K term from the mesh (drop one of the two)", NemoWarning, stacklevel=2)
    params = section_params(args, "defects")
    params["curvature_correction"] = False if args.no_curvature_correction else None
    intensity = director_params = None
    if args.layer:
        layer = read_table(args.layer, kind="layer", n_vertices=n)
        intensity = field_on_vertices(layer, "intensity", n, args.layer, exact=True)
        director_params = read_provenance(args.directors).get("parameters")
        if not director_params:
            raise NemoError(f"{args.directors} does not record the parameters it was measured with "
                            "(made by an older nemo?): recompute it, or drop --layer")
    df, extra, resolved = stages.defects(mesh, odf, ddf, params, avg_radius=avg, curvature=k,
                                         intensity=intensity, director_params=director_params)
    check = df.attrs["euler_check"]
    unit = getattr(mesh, "units", "um")
    prov = dict(mesh=str(args.mesh), n_vertices=n, unit=unit)
    write_table(df, out, command="defects", order=str(args.order), directors=str(args.directors),
                curvature=args.curvature, layer=args.layer, **prov, euler_check=check,
                parameters=resolved, find_parameters=df.attrs["parameters"])
    if args.refined:
        refined = extra if extra is not None else ddf.iloc[:0]
        write_table(refined, output_path(args.refined), command="defects refinement directors",
                    layer=args.layer, **prov, parameters=director_params)
    if cand_out is not None:
        from nemo.defects import candidate_table

        cands = candidate_table(df)
        write_table(cands, cand_out, command="defects candidates", order=str(args.order),
                    directors=str(args.directors), **prov, find_parameters=df.attrs["parameters"])
        rej = cands.loc[~cands["accepted"], "reason"].value_counts()
        print(f"{len(cands)} candidate(s), {len(cands) - int(cands['accepted'].sum())} rejected"
              + (f" ({', '.join(f'{k}: {v}' for k, v in rej.items())})" if len(rej) else "")
              + f" -> {cand_out}")
    _print_defects(df)
    p = df.attrs["parameters"]
    if p.get("skipped"):  # a frame without directors, or an object too small for the derived lengths
        print(f"no defect search ({p['skipped']}) -> {out}")
        return 0
    print(f"{len(df)} defect(s) (S < {p['s_threshold']:.3g}, contour {p['contour_radius']:.3g} {unit}, "
          f"K term: {p['curvature_source'] if p['curvature_correction'] else 'off'}; "
          f"{resolved['n_refine_directors']} refinement directors) -> {out}")
    if check["closed"]:
        verdict = "ok" if check["matches"] else "MISMATCH"
        print(f"Euler check: sum of charges {check['sum_charge']:.3f} (rounded {check['sum_charge_rounded']:g}) "
              f"vs chi = {check['euler_characteristic']}: {verdict}")
    else:
        print(f"Euler check: open surface (chi = {check['euler_characteristic']}), "
              f"sum of charges {check['sum_charge']:.3f}: no Poincaré-Hopf constraint")
    return 0


def _print_defects(df) -> None:
    """The defects found, one per line, and those where the fibres are faint."""
    from nemo.summary import QC_MIN_DEFECT_COHERENCY

    if not len(df):
        return
    cols = ["x", "y", "z", "S", "charge", "charge_winding", "charge_curvature", "charge_rounded", "coherency"]
    print(df[[c for c in cols if c in df]].to_string(float_format=lambda v: f"{v:.3f}", index=False))
    faint = int((df["coherency"] < QC_MIN_DEFECT_COHERENCY).sum()) if "coherency" in df else 0
    if faint:
        print(f"{faint} defect(s) with coherency below {QC_MIN_DEFECT_COHERENCY:g} of the surface's: the fibres there "
              "are faint, their positions uncertain (flagged in the summary)")
