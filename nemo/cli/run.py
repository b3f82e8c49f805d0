"""``nemo run``: the whole analysis of one frame, with the workflow's config."""

from __future__ import annotations

from nemo.cli.common import add_common, add_mask_arguments, mask_options

HELP = "one frame through the whole analysis (the workflow's steps, config and file names)"
DESCRIPTION = """\
Run the analysis of one (t, c) frame with the same steps, parameters and file names as the
workflow (nemo.stages, nemo.layout) and write every file into OUTDIR: mesh.ply (+ mesh.inner.ply,
mesh.outer.ply when split), measure_SURFACE.json, curvature_SURFACE.parquet, thickness.parquet,
and for each layer in channel C: layer_NAME, directors_NAME, order_NAME, defects_NAME,
refined_NAME (.parquet); align_A_B.parquet for alignment pairs; summary.json (resolved
parameters, timings, peak memory, Euler check).

--config takes the workflow's own config file unchanged (datasets, results, resources and
report are used for the frame it points at, or ignored). Without it the schema's defaults
apply: one layer 'fibres' [0, 5] µm outward from the inner wall; every length not given
follows the data (mesh edge length, object size; see --print-config). With the same config
the workflow and nemo run give the same numbers. --no-layers analyses the morphology only (a
membrane or a droplet without fibres: mesh, measure, curvature, thickness), as a config with
`layers: {}` does.

examples:
  nemo synth vesicle.tif && nemo run vesicle.tif -o results/vesicle
  nemo run --config config/config.yaml --dataset demo --t 1 -o out/demo_t1
  nemo run movie.tif --t 3 --c 1 --config my.yaml -o results/t3c1
  nemo run vesicle.tif --print-config          # every default resolved on this frame
  nemo run droplets.tif --no-layers -o out/droplets   # morphology only"""


def add_arguments(parser) -> None:
    parser.add_argument("image", nargs="?", help="TIFF hyperstack, OME-TIFF or OME-Zarr folder (default: the dataset's path)")
    parser.add_argument("--config", metavar="FILE", help="the workflow's YAML config (default: built-in defaults)")
    parser.add_argument("--dataset", metavar="NAME",
                        help="take image, spacing, psf, mask, segmented channel and overrides from datasets.NAME")
    parser.add_argument("--print-config", action="store_true",
                        help="print the parameters resolved on this frame (meshes it, no other output) and exit")
    parser.add_argument("--no-layers", action="store_true",
                        help="morphology only: no layers, directors, order, defects or alignment (the config's "
                             "layers and alignment are dropped; the quality control is the surfaces')")
    add_common(parser, frame=True, output_help="output folder", output_required=False)
    add_mask_arguments(parser)


def run(args) -> int:
    from nemo.cli.deconvolve import psf_note
    from nemo.errors import NemoError
    from nemo.pipeline import run_frame

    spacing = tuple(args.spacing) if args.spacing else None
    psf = args.psf
    mask = mask_options(args)
    if args.print_config:
        import yaml

        from nemo.pipeline import resolved_config

        print(yaml.safe_dump(resolved_config(args.image, args.config, t=args.t, c=args.c, spacing=spacing,
                                             dataset=args.dataset, psf=psf, mask=mask, layers=not args.no_layers),
                             sort_keys=False), end="")
        return 0
    if not args.output:
        raise NemoError("give an output folder with -o OUTDIR")
    summary = run_frame(args.image, args.output, args.config, t=args.t, c=args.c, spacing=spacing,
                        dataset=args.dataset, psf=psf, mask=mask, layers=not args.no_layers)
    dec = summary["mesh"].get("deconvolution") or {}
    note = f", {psf_note(dec)}" if dec.get("iterations") or dec.get("estimated") else ""
    print(f"{summary['image']} t={args.t} c={args.c}: mesh step {summary['mesh']['step']} voxels{note}")
    for name, res in summary["layers"].items():
        chk = res["euler_check"]
        order = f"mean S {res['S']['mean']:.3f}" if res["S"]["mean"] is not None else "no order (see the warnings)"
        print(f"layer {name} ({res['surface']} surface, {res['vertices']} vertices): {res['n_directors']} "
              f"directors, {order}")
        for d in res["defects"]:
            print(f"  defect at ({d['x']:.2f}, {d['y']:.2f}, {d['z']:.2f}) charge {d['charge']:+.3f} "
                  f"(~{d['charge_rounded']:+g}), S {d['S']:.3f}")
        if chk.get("skipped"):
            print(f"  no defect search: {chk['skipped']}")
            continue
        print(f"  {len(res['defects'])} defect(s), sum of charges {chk['sum_charge']:.3f} vs chi = "
              f"{chk['euler_characteristic']}{'' if chk['closed'] else ' (open surface)'}")
    _print_qc(summary["qc"])
    for pair in summary["alignment"]:
        print(_alignment_line(pair))
    print(f"done in {summary['total_s']:.1f} s, peak memory {summary['peak_rss_mb']:.0f} MB -> {args.output}")
    return 0


def _alignment_line(pair: dict) -> str:
    """One layer pair's alignment and its quality control (a row of the workflow's alignment.parquet)."""
    def signed(value) -> str:
        return "n/a" if value is None else f"{value:+.3f}"

    qc = "pass" if pair["qc_pass"] else "FAIL: " + pair["qc_flags"]
    return (f"alignment {pair['layer_a']} / {pair['layer_b']}: c_avg {signed(pair['c_avg_mean'])} (averaged directors, "
            f"S-weighted), mean c {signed(pair['c_mean'])} over {pair['n']} directors; quality control: {qc}")


#: Most quality-control rows printed one by one (more: counted per layer, the rows in summary.json).
QC_ROWS_PRINTED = 10


def _print_qc(rows: list[dict]) -> None:
    """The frame's quality control, a line per layer (or surface) and object; with many objects (a
    tissue's nuclei) a line per layer and surface with the passes and the commonest kinds of flag
    (a flag's numbers left out: "Σ charge … ≠ χ …")."""
    import re
    from collections import Counter

    from nemo.summary import FLAG_SEPARATOR

    def what(q: dict, many: bool) -> str:
        return " ".join(x for x in (q["layer"] and f"layer {q['layer']}", q["surface"],
                                    many and f"object {q['object']}") if x)

    if len(rows) <= QC_ROWS_PRINTED:
        many = len({q["object"] for q in rows}) > 1
        for q in rows:
            print(f"quality control ({what(q, many)}): {'pass' if q['qc_pass'] else 'FAIL: ' + q['qc_flags']}")
        return
    for key in dict.fromkeys((q["layer"], q["surface"]) for q in rows):
        mine = [q for q in rows if (q["layer"], q["surface"]) == key]
        kinds = Counter(re.sub(r"-?\d[\d.]*", "…", f.split(": ")[0]) for q in mine
                        for f in q["qc_flags"].split(FLAG_SEPARATOR) if f)
        common = ", ".join(f"{kind} ({n})" for kind, n in kinds.most_common(3))
        print(f"quality control ({what(mine[0], False)}): {sum(q['qc_pass'] for q in mine)} of {len(mine)} objects "
              f"pass" + (f"; commonest flags: {common}" if common else "") + " (each object: summary.json's qc)")
