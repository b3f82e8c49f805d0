"""``nemo run``: the whole chain for one frame of an image."""

from __future__ import annotations

from nemo.cli.common import add_common

HELP = "one frame through mesh -> peel -> directors -> order -> curvature -> defects"
DESCRIPTION = """\
Run the whole analysis of one (t, c) frame and write every intermediate file into OUTDIR:
mesh.ply, mesh.inner.ply, mesh.outer.ply, layer.parquet, directors.parquet, directors.defects.parquet (refinement), order.parquet,
curvature.parquet, defects.parquet and summary.json (parameters, timings, peak memory, Euler
check). Defaults are the paper's for its synthetic vesicle (marching-cubes step 2 µm, layer
[0, 5] µm outward from the inner wall, 12 000 director patches of 20 µm, 50 µm averaging). A
YAML --config overrides any of them by section, e.g.

  order:
    radius: 30
  peel:
    range: [1, 4]

(sections: mesh, peel, directors, order, curvature, defects; unknown keys are an error).

example:
  nemo synth vesicle.tif && nemo run vesicle.tif -o results/vesicle
  nemo run movie.tif --t 3 --c 1 --config my.yaml -o results/t3c1"""


def add_arguments(parser) -> None:
    parser.add_argument("image", help="TIFF hyperstack or OME-TIFF")
    parser.add_argument("--config", metavar="FILE", help="YAML file overriding the default parameters")
    parser.add_argument("--print-config", action="store_true",
                        help="print the effective parameters as YAML and exit")
    add_common(parser, frame=True, output_help="output folder", output_required=False)


def run(args) -> int:
    from nemo.errors import NemoError
    from nemo.pipeline import load_config, run_frame

    if args.print_config:
        import yaml

        print(yaml.safe_dump(load_config(args.config), sort_keys=False), end="")
        return 0
    if not args.output:
        raise NemoError("give an output folder with -o OUTDIR")
    summary = run_frame(args.image, args.output, args.config, t=args.t, c=args.c,
                        spacing=tuple(args.spacing) if args.spacing else None)
    chk = summary["euler_check"]
    print(f"{summary['mesh']['surface']} surface: {summary['mesh']['vertices']} vertices; "
          f"{summary['n_directors']} directors; mean S {summary['S']['mean']:.3f}")
    for d in summary["defects"]:
        print(f"  defect at ({d['x']:.2f}, {d['y']:.2f}, {d['z']:.2f}) charge {d['charge']:+.3f} "
              f"(~{d['charge_rounded']:+g}), S {d['S']:.3f}")
    print(f"{len(summary['defects'])} defect(s), sum of charges {chk['sum_charge']:.3f} vs chi = "
          f"{chk['euler_characteristic']}{'' if chk['closed'] else ' (open surface)'}")
    print(f"done in {summary['total_s']:.1f} s, peak memory {summary['peak_rss_mb']:.0f} MB -> {args.output}")
    return 0
