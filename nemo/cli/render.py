"""``nemo render``: figures (PNG) of one frame's results, or of a dataset's summaries."""

from __future__ import annotations

from pathlib import Path

from nemo.cli.common import add_common

HELP = "PNG figures of a frame's results (surface renders, maps, distributions) or of a time-lapse"
DESCRIPTION = """\
Render the figures of one frame: pyvista off-screen renders of the surface coloured by the
peeled intensity, by S with the averaged directors, with the defects marked by charge, and by
H, K, thickness; matplotlib figures of the S and charge distributions, a spherical-coordinate
map (intensity + directors + defects), morphology maps and the inter-layer alignment.
With --summary: per layer the defect tracks and a map of every frame's defects over time
(tracks_<layer>.png, defect_map_<layer>.png), and frames.png: S, defects, total charge vs the
Euler characteristic, thickness, mean curvature, area and volume versus t, with units and the
per-frame quality-control flags.

Inputs are a frame folder or its files (meshes *.ply, tables *.parquet named as in
docs/viewing.md), so a workflow rule can list its inputs explicitly. The output folder gets
one PNG per figure and figures.json (file -> kind, caption, sources, parameters).
No X server is needed (VTK renders through EGL/OSMesa).

examples:
  nemo render results/demo/t0/c0 -o figures/demo/t0/c0
  nemo render results/demo/t0/c0/mesh.inner.ply results/demo/t0/c0/layer_a.parquet \\
      results/demo/t0/c0/order_a.parquet results/demo/t0/c0/defects_a.parquet -o figs --layer a
  nemo render --summary results/demo/summary -o figures/demo/summary
  nemo render results/demo/t0/c0 -o figs --list     # print the figure names only"""


def add_arguments(parser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="frame folder, or its mesh and table files (with --summary: the "
                             "summary folder or its tables)")
    parser.add_argument("--layer", action="append", metavar="L",
                        help="render only this layer (repeatable; default every layer found)")
    parser.add_argument("--summary", action="store_true",
                        help="inputs are summary tables (defects.parquet with track_id, frames.parquet)")
    parser.add_argument("--image", metavar="TIFF", help="hyperstack (recorded in figures.json only)")
    parser.add_argument("--no-surfaces", action="store_true",
                        help="skip the pyvista surface renders (matplotlib figures only)")
    parser.add_argument("--list", action="store_true",
                        help="print the names of the figures the inputs give, render nothing")
    add_common(parser, output_help="output folder for the PNG files", output_required=False)


def run(args) -> int:
    from nemo.errors import NemoError
    from nemo.layout import discover_frame
    from nemo.render import planned_figures, render_frame, render_summary

    if args.summary:
        if args.list:
            raise NemoError("--list works for frames only (summary figures: tracks_<layer>.png, "
                            "defect_map_<layer>.png, frames.png)")
        if not args.output:
            raise NemoError("give the output folder with -o OUTDIR")
        figs = render_summary(args.inputs, args.output, layers=args.layer)
    else:
        files = discover_frame(args.inputs if len(args.inputs) > 1 else args.inputs[0], image=args.image)
        if args.list:
            for name in planned_figures(files, args.layer):
                if args.no_surfaces and name.startswith("surface_"):
                    continue
                print(name)
            return 0
        if not args.output:
            raise NemoError("give the output folder with -o OUTDIR")
        figs = render_frame(files, args.output, layers=args.layer,
                            surface_renders=not args.no_surfaces)
    for f in figs:
        print(Path(f.path))
    return 0
